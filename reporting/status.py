"""``surprise-master status DIR``: where a run stands, in a few lines, from its files alone."""

from __future__ import annotations

import time
from pathlib import Path

from minimize_surprise.text import format_duration, plural
from runfiles import schema
from runfiles.schema import (
    Checkpoint,
    Live,
    PauseFile,
    PostEvaluation,
    QDSummary,
    Software,
    SoftwareRecord,
    master_alive,
)

__all__ = ["running_master", "software_lines", "status_text"]

#: Characters of a commit shown (git takes them as the commit's name).
SHORT_COMMIT = 10


def running_master(path: str | Path) -> Live | None:
    """``live.json`` of the master serving the run in ``path`` now; None when none does (never
    started, stopped, silent for too long, or a file this version cannot read)."""
    live = schema.read_if_readable(path, Live)
    return live if master_alive(live, time.time()) else None


def status_text(path: str | Path) -> str:
    """Where the run in ``path`` stands, in a few lines."""
    path = Path(path)
    qd = schema.read_if_readable(path, QDSummary)
    if qd is not None:
        return _qd_status(path, qd)
    config = schema.read_config(path)
    assert config.experiment is not None
    planned = config.experiment.evolution.evaluations or "endless"
    checkpoint = schema.read(path, Checkpoint)
    lines = [f"run {path.resolve().name} ({path})"]
    if checkpoint is None:
        lines.append(f"phase: not started, 0/{planned} evaluations")
    else:
        best = checkpoint.best_fitness
        lines.append(
            f"phase: {checkpoint.phase}, {checkpoint.evaluations}/{planned} "
            f"evaluations counted, "
            f"{plural(checkpoint.failed_attempts, 'failed attempt')}"
        )
        lines.append("best fitness: " + ("-" if best is None else f"{best:.4f}"))
        rows = schema.read_rows(path)[: checkpoint.csv_rows]
        if rows:
            last = rows[-1]
            lines.append(
                f"last evaluation: {last['evaluation']} {last['kind']}, fitness "
                f"{float(last['fitness']):.4f}, accepted {last['accepted']}"
            )
        lines.append(f"served for {format_duration(checkpoint.elapsed_s)}")
        for change in checkpoint.swarms or ():
            how = f"{change.joined} in its place" if change.joined else "the run went on without it"
            lines.append(
                f"swarm changed from evaluation {change.from_evaluation}: {change.left} gone, "
                f"{how}; now {', '.join(change.robots)}"
            )
    live = running_master(path)
    roster = None if checkpoint is None else checkpoint.roster
    swarm_size = config.robot_count if roster is None else len(roster)
    if live is not None:
        lines.append(
            f"master: running (pid {live.pid}, {live.host}:{live.port}), "
            f"robots connected {len(live.robots)}/{swarm_size}: "
            f"{', '.join(live.robots) or '-'}"
        )
        if live.time_left_s is not None:
            lines.append(f"time left: ~{format_duration(live.time_left_s)}")
        pause = schema.read_if_readable(path, PauseFile)
        if pause is not None:
            lines.append(f"paused: {pause.reason}; then: surprise-master continue {path}")
        batteries = [
            f"{robot} {state['battery_v']:.2f} V"
            for robot, state in sorted(live.robot_state.items())
            if isinstance(state.get("battery_v"), int | float)
        ]
        if batteries:
            lines.append("batteries: " + ", ".join(batteries))
    elif checkpoint is None or checkpoint.phase != "done":
        lines.append(f"master: not running; continue with `surprise-master resume {path}`")
    else:
        lines.append("master: not running; the run is complete")
    lines += software_lines(schema.read_if_readable(path, SoftwareRecord))
    post = schema.read(path, PostEvaluation)
    if post is not None:
        fitness = post.swarm_fitness
        lines.append(
            "post-evaluation: done, swarm fitness "
            + ("-" if fitness is None else f"{fitness:.4f}")
            + f", traces of {len(post.robots)} robots"
        )
    return "\n".join(lines)


def software_lines(record: SoftwareRecord | None) -> list[str]:
    """The master's software and each robot's as it last joined (``software.json``), robots on
    other software than the master's marked; nothing for a run that has no record."""
    if record is None:
        return []
    lines = [f"software: master {_software(record.master)}"]
    for robot, software in sorted(record.robots.items()):
        differs = (software.version, software.commit) != (
            record.master.version,
            record.master.commit,
        )
        lines.append(
            f"  {robot}: {_software(software)}, firmware "
            + ("?" if software.firmware is None else str(software.firmware))
            + (" (other software than the master's)" if differs else "")
        )
    return lines


def _software(software: Software) -> str:
    commit = software.commit
    if commit is None:
        return f"{software.version}, commit unknown"
    dirty = commit.endswith("-dirty")
    short = commit.removesuffix("-dirty")[:SHORT_COMMIT] + (" with changes" if dirty else "")
    return f"{software.version} {short}"


def _qd_status(path: Path, qd: QDSummary) -> str:
    # A MAP-Elites run (docs/quality-diversity.md) has an archive, not a best genome.
    planned = qd.experiment.evolution.evaluations
    lines = [
        f"run {path.resolve().name} ({path}): MAP-Elites",
        f"phase: {'done' if qd.done else 'evolving'}, {qd.evaluations}/{planned} evaluations, "
        f"served for {format_duration(qd.seconds)}",
        f"archive: {qd.cells} cells filled (coverage {qd.coverage:.3f}), QD score "
        f"{qd.qd_score:.1f}",
    ]
    for name, elite in sorted(qd.classes.items()):
        post = ""
        if elite.post_fitness is not None:
            post = f", post-evaluated {elite.post_fitness:.4f} ({elite.post_class})"
        lines.append(f"  {name}: best elite {elite.fitness:.4f}{post}")
    return "\n".join(lines)
