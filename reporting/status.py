"""``surprise-master status DIR``: where a run stands, in a few lines, from its files alone."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Final

from master_service.evaluation import format_duration
from master_service.master import LIVE_INTERVAL
from master_service.pause import read_pause
from master_service.rundir import LIVE, POST_EVALUATION, RunDir
from minimize_surprise.text import plural

__all__ = ["running_master", "status_text"]

#: A live.json older than this many refresh periods means the master is gone.
_STALE_PERIODS: Final = 5


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def running_master(run: RunDir) -> dict[str, Any] | None:
    """``live.json`` of the master serving ``run`` now, None when none does (never started,
    stopped, or silent for too long)."""
    live = run.read_json(LIVE)
    fresh = (
        isinstance(live, dict)
        and live.get("running")
        and time.time() - float(live.get("updated_at", 0)) < _STALE_PERIODS * LIVE_INTERVAL
        and _alive(int(live.get("pid", -1)))
    )
    return live if fresh and isinstance(live, dict) else None


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
    live = running_master(run)
    if live is not None:
        robots = live.get("robots", [])
        lines.append(
            f"master: running (pid {live['pid']}, {live['host']}:{live['port']}), "
            f"robots connected {len(robots)}/{config.robot_count}: {', '.join(robots) or '-'}"
        )
        if live.get("time_left_s") is not None:
            lines.append(f"time left: ~{format_duration(live['time_left_s'])}")
        pause = read_pause(run)
        if pause is not None:
            lines.append(
                f"paused: {pause.get('reason', '?')}; then: surprise-master continue {run.path}"
            )
        batteries = [
            f"{robot} {state['battery_v']:.2f} V"
            for robot, state in sorted((live.get("robot_state") or {}).items())
            if state.get("battery_v") is not None
        ]
        if batteries:
            lines.append("batteries: " + ", ".join(batteries))
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
