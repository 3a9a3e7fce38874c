"""What a run amounts to: ``metrics.json``, pictures, and the one-screen status.

Metrics: the evolution's (best, mean, offspring accepted, attempts), the share of steps in which
the safety layer changed the networks' commands (per evaluation in ``evaluations.csv``; here its
mean over the run, over its last tenth and over the post-evaluation, with a warning when it
dominates), and from the post-evaluation traces each sensor's mean prediction and reading; when
the traces hold poses (simulation) the behaviour metrics of docs/method.md (d_R, c_o, mean
cluster size and their classes, the box displacement d_B from ``simulation.json``) and per robot
its path length and rotation; a real run's the same from a tracker's file (:mod:`.tracker`).

Pictures (``plots/``, each as PNG and PDF; :mod:`reporting.pictures`): ``fitness``,
``robot_fitness``, ``predictions``, for a run whose arena changed ``recovery`` (and its table
``recovery.md``, :mod:`reporting.recovery`), in simulation ``trajectories`` on the arena, with a
baseline ``evolved_vs_random``; with ``animate`` also ``post_evaluation.gif``.
"""

from __future__ import annotations

import collections
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import msgspec
import numpy as np

from minimize_surprise.config import ExperimentConfig
from minimize_surprise.dominance import dominance, ground_at_start
from minimize_surprise.errors import ConfigError
from minimize_surprise.safety import intervention_reasons, intervention_share
from reporting import pictures, reality_gap, tracker
from reporting.recovery import recoveries, recovery_metrics, recovery_picture, recovery_table
from reporting.robot_stats import parse_robot_stats, robot_stats
from runfiles import schema
from runfiles.schema import (
    BOX_TRACK,
    METRICS,
    PLOTS,
    BoxesMoved,
    Checkpoint,
    PostEvaluation,
    Replay,
    RunDirError,
    Simulation,
    load_baseline,
    write_atomic,
    writing,
)
from simulator import metrics as sim_metrics
from simulator.experiment import world_config

__all__ = [
    "NO_POSITIONS",
    "baseline_text",
    "behaviour_line",
    "compute_metrics",
    "safety_lines",
    "write_report",
]

#: Why a run has no behaviour class: the metrics are computed from positions, which a simulated
#: robot's trace carries and a real robot's does not (it does not know where it is).
NO_POSITIONS: Final = (
    "the post-evaluation's traces hold no positions (a real robot does not know where it is), "
    "and the behaviour metrics are computed from them"
)


def _rows(run: Path, limit: int | None) -> tuple[list[dict[str, Any]], list[str]]:
    # Rows past the checkpoint's count belong to an unfinished commit (resume drops them); the
    # last of them may be torn, so they are cut before being parsed.
    rows = schema.read_rows(run)[:limit]
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
                # Runs written before the column existed have none.
                "safety_share": (
                    float(row["safety_share"])
                    if row.get("safety_share") not in (None, "")
                    else None
                ),
                # A robot that left the swarm, or joined it later, has empty cells where it was
                # not in the swarm (docs/runs.md): those rows hold no fitness of it.
                "robots": {
                    robot: float(row[f"fitness_{robot}"])
                    for robot in robots
                    if row.get(f"fitness_{robot}")
                },
                "robot_stats": parse_robot_stats(row, robots),
            }
        )
    return typed, robots


def _traces(run: Path, post: PostEvaluation | None) -> dict[str, dict[str, np.ndarray]]:
    traces: dict[str, dict[str, np.ndarray]] = {}
    if post is None:
        return traces
    for robot, entry in post.robots.items():
        if entry.trace:
            with np.load(run / entry.trace) as data:
                traces[robot] = {key: data[key] for key in data.files}
    return traces


def _post_metrics(
    post: PostEvaluation,
    traces: dict[str, dict[str, np.ndarray]],
    sensors: list[str],
    simulation: Simulation | None,
    dt: float,
    tracked_boxes: BoxesMoved | None = None,
) -> dict[str, Any]:
    robots: dict[str, Any] = {}
    predicted: list[np.ndarray] = []
    real: list[np.ndarray] = []
    poses: dict[str, np.ndarray] = {}
    for robot, entry in post.robots.items():
        info: dict[str, Any] = {
            "fitness": entry.fitness,
            "stats": msgspec.to_builtins(entry.stats),
        }
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
        "steps": post.steps,
        "genome_fitness": post.genome_fitness,
        "swarm_fitness": post.swarm_fitness,
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
        # A simulated run's boxes, or those an overhead camera found for a real one.
        boxes = tracked_boxes if simulation is None else simulation.post_evaluation_boxes
        behaviour = sim_metrics.behaviour_metrics(
            stacked,
            None if boxes is None else np.asarray(boxes.start, dtype=np.float64),
            None if boxes is None else np.asarray(boxes.end, dtype=np.float64),
            dt=dt,
        )
        metrics["behaviour"] = msgspec.to_builtins(behaviour)
    else:
        metrics["behaviour_missing"] = NO_POSITIONS
    return metrics


def _safety_metrics(
    rows: list[dict[str, Any]],
    post: PostEvaluation | None,
    traces: dict[str, dict[str, np.ndarray]],
) -> dict[str, Any] | None:
    """How much the safety layer drove: over the run, its last tenth and the post-evaluation."""
    metrics: dict[str, Any] = {}
    shares = [r["safety_share"] for r in rows if r["safety_share"] is not None]
    if shares:
        tail = shares[-max(1, len(shares) // 10) :]
        metrics["evolution_mean_share"] = float(np.mean(shares))
        metrics["last_tenth_share"] = float(np.mean(tail))
    counts: list[dict[str, int]] = []
    if post is not None and post.robots:
        stats = {robot: entry.stats for robot, entry in post.robots.items()}
        counts = [e.interventions for e in stats.values()]
        metrics["post_evaluation_share"] = intervention_share(
            counts, sum(e.steps_run for e in stats.values())
        )
        metrics["post_evaluation_reasons"] = dict(intervention_reasons(counts).most_common())
        metrics["post_evaluation_robots"] = {
            robot: intervention_share([e.interventions], e.steps_run) for robot, e in stats.items()
        }
    if not metrics:
        return None
    # The post-evaluation is what the behaviour is judged on, the end of the evolution what the
    # best genome was selected on: either dominated by the safety layer is said, as a warning
    # when a person should act on it, else as a note on the behaviour (minimize_surprise.dominance).
    warnings: list[str] = []
    notes: list[str] = []
    post_found = None
    if "post_evaluation_share" in metrics:
        at_start = ground_at_start(t["safety"] for t in traces.values() if "safety" in t)
        post_found = dominance(metrics["post_evaluation_share"], counts, at_start=at_start)
        if post_found is not None:
            said = warnings if post_found.actionable else notes
            said.append(f"in the post-evaluation {post_found.text}")
    if "last_tenth_share" in metrics:
        found = dominance(metrics["last_tenth_share"], [])
        if found is not None:
            # The rows keep no reasons: the post-evaluation's, of the genome the evolution ended
            # on, say what it was; without one it is worth a look.
            actionable = post_found is None or post_found.actionable
            text = found.text if actionable else _evolution_note(metrics["last_tenth_share"])
            (warnings if actionable else notes).append(f"in the last tenth of the evolution {text}")
    metrics["warnings"] = warnings
    metrics["notes"] = notes
    return metrics


def _evolution_note(share: float) -> str:
    return (
        f"the safety layer drove {100 * share:.0f} % of the steps, for the reason the "
        "post-evaluation shows; an outcome of the evolution, not a fault"
    )


@dataclass
class _Run:
    """Everything a report reads from a run directory, read once."""

    run: Path
    experiment: ExperimentConfig
    checkpoint: Checkpoint | None
    rows: list[dict[str, Any]]
    robots: list[str]
    post: PostEvaluation | None
    traces: dict[str, dict[str, np.ndarray]]
    simulation: Simulation | None
    tracked: dict[str, Any] | None = None  # where a tracker's file gave the poses
    tracked_boxes: BoxesMoved | None = None  # the boxes the tracker found, paired


def _load(
    path: str | Path, positions: str | Path | None = None, offset: float | None = None
) -> _Run:
    run = Path(path)
    config = schema.read_config(run)
    assert config.experiment is not None
    checkpoint = schema.read(run, Checkpoint)
    rows, robots = _rows(run, None if checkpoint is None else checkpoint.csv_rows)
    post = schema.read(run, PostEvaluation)
    simulation = schema.read(run, Simulation)
    traces = _traces(run, post)
    # A tracker's poses stand where a simulated trace holds them: all is computed as for one.
    tracked = tracker.add_tracked_poses(
        positions, traces, config.experiment.step_period, offset=offset, ignore=robots
    )
    boxes = None
    if tracked is not None and positions is not None and simulation is None:
        found = tracker.tracked_boxes(positions)
        if found is not None:
            boxes, tracked["boxes"] = found
    return _Run(
        run, config.experiment, checkpoint, rows, robots, post, traces, simulation, tracked, boxes
    )


def compute_metrics(path: str | Path) -> dict[str, Any]:
    """The metrics of the run in ``path`` as plain data (what ``metrics.json`` holds)."""
    return _metrics(_load(path))


def _metrics(data: _Run) -> dict[str, Any]:
    run, checkpoint, rows, robots = data.run, data.checkpoint, data.rows, data.robots
    metrics: dict[str, Any] = {
        "run_id": run.resolve().name if checkpoint is None else checkpoint.run_id,
        "phase": "evolution" if checkpoint is None else checkpoint.phase,
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
            failed_attempts=None if checkpoint is None else checkpoint.failed_attempts,
            duration_s=float(sum(r["duration_s"] for r in rows)),
            robot_fitness={
                robot: {
                    "mean": float(np.mean(values)),
                    "max": float(np.max(values)),
                }
                for robot in robots
                if (values := [r["robots"][robot] for r in rows if robot in r["robots"]])
            },
        )
    changes = recoveries([r["fitness"] for r in rows], schema.read_events(run))
    if changes:  # the arena changed, or a person marked a change (docs/changing-arenas.md)
        metrics["recovery"] = recovery_metrics(changes)
    metrics["robot_stats"] = robot_stats(rows, robots)
    metrics["safety"] = _safety_metrics(rows, data.post, data.traces)
    metrics["warnings"] = list((metrics["safety"] or {}).get("warnings", []))
    metrics["post_evaluation"] = (
        None
        if data.post is None
        else _post_metrics(
            data.post,
            data.traces,
            list(data.experiment.sensors),
            data.simulation,
            data.experiment.step_period,
            data.tracked_boxes,
        )
    )
    if data.tracked is not None and metrics["post_evaluation"] is not None:
        metrics["post_evaluation"]["positions"] = data.tracked
    replay = schema.read(run, Replay)
    if replay is not None and replay.source_run:
        source = Path(replay.source_run)
        # The source's metrics as its own report computes them (its metrics.json may be stale).
        source_metrics = compute_metrics(source) if source.is_dir() else {}
        metrics["reality_gap"] = reality_gap.compare(source_metrics, metrics, str(source))
    return metrics


def _baseline_metrics(metrics: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    pairs = baseline["pairs"]
    random_fitness = [pair["fitness"] for pair in pairs]
    evolved = metrics.get("best_fitness")
    post = (metrics.get("post_evaluation") or {}).get("swarm_fitness")
    return {
        "scenario": baseline["scenario"],
        "random_pairs": len(random_fitness),
        "random_fitness": random_fitness,
        "random_median_fitness": float(np.median(random_fitness)),
        "random_best_fitness": float(np.max(random_fitness)),
        # The random pairs' fitness over the whole post-evaluation length, beside the evolved
        # genome's post-evaluation.
        "random_best_post_fitness": max(pair["post_fitness"] for pair in pairs),
        # Best of a run against best of the random pairs: both are a maximum over many tries.
        "evolved_best_fitness": evolved,
        "evolved_post_fitness": post,
        "random_pairs_below_evolved_best": (
            None if evolved is None else sum(f < evolved for f in random_fitness)
        ),
        "random_behaviour_counts": {
            key: dict(collections.Counter(pair["behaviour"][key] for pair in pairs).most_common())
            for key in ("motion", "grouping", "manipulation")
            if any(pair["behaviour"].get(key) is not None for pair in pairs)
        },
    }


def write_report(
    path: str | Path,
    *,
    baseline: str | Path | None = None,
    plots: bool = True,
    animate: bool = False,
    positions: str | Path | None = None,
    positions_offset: float | None = None,
) -> dict[str, Any]:
    """Write ``metrics.json`` and (with ``plots``) the pictures of the run in ``path``; return
    the metrics (``pictures``: the files drawn, relative to ``path``).

    ``baseline`` names a ``surprise-master baseline`` directory: the metrics then compare the
    evolved best fitness with the random pairs' (``baseline`` key), with a picture. ``animate``
    also writes an animation of a simulated post-evaluation (``plots/post_evaluation.gif``).
    ``positions``: a tracker's CSV file giving a real run's poses, its time ``positions_offset``
    the first step's (:func:`.tracker.add_tracked_poses`; a bad file writes nothing).
    """
    data = _load(path, positions, positions_offset)
    metrics = _metrics(data)
    if baseline is not None:
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
    if plots or animate:
        drawn = _draw(data, metrics, plots=plots, animate=animate)
        metrics["pictures"] = [str(p.relative_to(data.run)) for p in drawn]
    write_atomic(data.run / METRICS, json.dumps(metrics, indent=2).encode("utf-8"))
    return metrics


def behaviour_line(metrics: dict[str, Any]) -> str | None:
    """The post-evaluation's behaviour class in a line, or why there is none (None before a
    post-evaluation)."""
    post = metrics.get("post_evaluation")
    if not post:
        return None
    b = post.get("behaviour")
    if not b:
        return f"behaviour: none: {post.get('behaviour_missing', NO_POSITIONS)}"
    kind = sim_metrics.behaviour_label(b)
    if post.get("positions"):
        source = post["positions"]
        boxes = source.get("boxes")
        also = f", d_B from the boxes in {boxes['file']}" if boxes else ""
        kind += f" (positions from {source['file']}{also})"
    return f"behaviour: {kind}"


def safety_lines(metrics: dict[str, Any]) -> list[str]:
    """How much the safety layer drove, in a line, and a note or a warning if it dominated."""
    safety = metrics.get("safety")
    if not safety:
        return []
    parts = []
    if safety.get("post_evaluation_share") is not None:
        parts.append(f"{100 * safety['post_evaluation_share']:.0f} % of the post-evaluation steps")
    if safety.get("evolution_mean_share") is not None:
        parts.append(
            f"{100 * safety['evolution_mean_share']:.0f} % of the evolution's "
            f"({100 * safety['last_tenth_share']:.0f} % in its last tenth)"
        )
    lines = [f"safety layer drove: {'; '.join(parts)}"] if parts else []
    lines += [f"note: {note}" for note in safety.get("notes", [])]
    lines += [f"warning: {warning}" for warning in safety.get("warnings", [])]
    return lines


def baseline_text(comparison: dict[str, Any]) -> str:
    """The evolved run against the random pairs, best of each, in a line."""
    pairs = comparison["random_pairs"]
    evolved = comparison["evolved_best_fitness"]
    text = (
        f"best random pair {comparison['random_best_fitness']:.4f} (median "
        f"{comparison['random_median_fitness']:.4f}, {pairs} pairs)"
    )
    if evolved is None:
        return f"no evolved fitness yet; {text}"
    below = comparison["random_pairs_below_evolved_best"]
    return (
        f"evolved best fitness {evolved:.4f} against the {text}: above {below} of {pairs} "
        "random pairs"
    )


def _title(data: _Run, metrics: dict[str, Any]) -> str:
    experiment = data.experiment
    where = f"{experiment.setting} setting" if data.simulation is not None else "robots"
    return f"{experiment.place} ({where}), run {metrics['run_id']}"


def _arena(data: _Run) -> pictures.Arena | None:
    """The run's world as the pictures draw it (real robots: their experiment's, if tracked, with
    the boxes the tracker found)."""
    if data.simulation is None and not data.tracked:
        return None
    config = world_config(data.experiment)
    simulated = data.simulation
    boxes = data.tracked_boxes if simulated is None else simulated.post_evaluation_boxes
    track, every = None, 1
    path = data.run / BOX_TRACK
    if path.is_file():
        with np.load(path) as stored:
            track, every = stored["positions"], int(stored["every"])
    return pictures.Arena(
        config,
        boxes_start=np.asarray(boxes.start) if boxes is not None and boxes.start else None,
        boxes_end=np.asarray(boxes.end) if boxes is not None and boxes.end else None,
        box_track=track,
        box_every=every,
    )


def _draw(data: _Run, metrics: dict[str, Any], *, plots: bool, animate: bool) -> list[Path]:
    """Draw the run's pictures into ``plots/``; the paths written."""
    directory = data.run / PLOTS
    with writing(directory):
        directory.mkdir(exist_ok=True)
    title = _title(data, metrics)
    post = metrics.get("post_evaluation") or {}
    poses = {robot: t["poses"] for robot, t in data.traces.items() if "poses" in t}
    arena = _arena(data) if poses else None
    drawn: list[Path] = []
    if plots:
        if data.rows:
            drawn += pictures.fitness_picture(
                directory,
                data.rows,
                title,
                post_fitness=post.get("swarm_fitness"),
                post_steps=post.get("steps"),
            )
            drawn += pictures.robot_fitness_picture(directory, data.rows, data.robots, title)
        if metrics.get("recovery"):
            fitness = [r["fitness"] for r in data.rows]
            found = recoveries(fitness, schema.read_events(data.run))
            drawn += recovery_picture(directory, fitness, found, title)
            write_atomic(directory / "recovery.md", recovery_table(found).encode())
            drawn.append(directory / "recovery.md")
        if post.get("sensors"):
            drawn += pictures.predictions_picture(directory, post["sensors"], title)
        comparison = metrics.get("baseline")
        if comparison:
            drawn += pictures.baseline_picture(directory, comparison, title)
        if metrics.get("reality_gap"):
            drawn += reality_gap.gap_picture(directory, metrics["reality_gap"], title)
        if poses:
            seconds = min(len(p) for p in poses.values()) * data.experiment.step_period
            drawn += pictures.trajectories_picture(
                directory,
                poses,
                arena,
                f"{title}\npost-evaluation of the best genome, {seconds:g} s",
            )
    if animate:
        if arena is None:
            raise RunDirError(
                f"{data.run} holds no simulated post-evaluation with poses to animate"
            )
        drawn.append(
            pictures.animate_post_evaluation(
                directory / pictures.ANIMATION,
                poses,
                arena,
                title,
                data.experiment.step_period,
            )
        )
    return drawn
