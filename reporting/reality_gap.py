"""The reality gap: a replay beside the post-evaluation its genome came from (docs/runs.md).

A replay (``surprise-master replay``) drives a stored genome on other robots: real ones, Aseba
Playground's, or simulated ones again. Its report compares it with the source run's own
post-evaluation: the swarm's fitness, each robot's (robot by robot in the order of their ids,
which need not match: ``sim-0`` beside ``thymio-1``), the behaviour class, and the share of steps
the safety layer drove. One table (:func:`gap_lines`) and one figure (:func:`gap_picture`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from reporting import pictures
from simulator.metrics import behaviour_label

__all__ = ["compare", "gap_lines", "gap_picture"]


def compare(source: dict[str, Any], replay: dict[str, Any], source_path: str) -> dict[str, Any]:
    """The gap between the metrics of the source run (``source``) and of the replay."""
    source_post = source.get("post_evaluation") or {}
    replay_post = replay.get("post_evaluation") or {}
    source_robots = _robot_fitness(source_post)
    replay_robots = _robot_fitness(replay_post)
    rows = []
    for i in range(max(len(source_robots), len(replay_robots))):
        s = source_robots[i] if i < len(source_robots) else (None, None)
        r = replay_robots[i] if i < len(replay_robots) else (None, None)
        rows.append(
            {
                "source_robot": s[0],
                "source_fitness": s[1],
                "replay_robot": r[0],
                "replay_fitness": r[1],
            }
        )
    swarm = {
        "source": source_post.get("swarm_fitness"),
        "replay": replay_post.get("swarm_fitness"),
    }
    if swarm["source"] is not None and swarm["replay"] is not None:
        swarm["gap"] = swarm["replay"] - swarm["source"]
    return {
        "source_run": source_path,
        "steps": {"source": source_post.get("steps"), "replay": replay_post.get("steps")},
        "swarm_fitness": swarm,
        "behaviour": {"source": _behaviour(source_post), "replay": _behaviour(replay_post)},
        "safety_share": {
            "source": (source.get("safety") or {}).get("post_evaluation_share"),
            "replay": (replay.get("safety") or {}).get("post_evaluation_share"),
        },
        "robots": rows,
    }


def _robot_fitness(post: dict[str, Any]) -> list[tuple[str, float]]:
    robots = post.get("robots") or {}
    return sorted((robot, float(r["fitness"])) for robot, r in robots.items())


def _behaviour(post: dict[str, Any]) -> str:
    b = post.get("behaviour")
    return behaviour_label(b) if b else "none (no positions)"


def gap_lines(gap: dict[str, Any] | None) -> list[str]:
    """The gap as a small table for a person."""
    if not gap:
        return []

    def number(value: float | None, digits: int = 4) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    def share(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.0f} %"

    swarm, safety = gap["swarm_fitness"], gap["safety_share"]
    rows = [
        ("", "source run", "replay"),
        ("swarm fitness", number(swarm["source"]), number(swarm["replay"])),
        ("behaviour", gap["behaviour"]["source"], gap["behaviour"]["replay"]),
        ("safety drove", share(safety["source"]), share(safety["replay"])),
        ("steps", str(gap["steps"]["source"]), str(gap["steps"]["replay"])),
    ]
    for row in gap["robots"]:
        rows.append(
            (
                "robot",
                f"{row['source_robot'] or '-'} {number(row['source_fitness'])}",
                f"{row['replay_robot'] or '-'} {number(row['replay_fitness'])}",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    text = [f"reality gap: this replay beside the post-evaluation of {gap['source_run']}"]
    text += ["  " + "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
             for r in rows]  # fmt: skip
    if swarm.get("gap") is not None:
        text.append(f"  gap in swarm fitness: {swarm['gap']:+.4f}")
    return text


def gap_picture(directory: Path, gap: dict[str, Any], title: str) -> list[Path]:
    """``reality_gap``: each robot's fitness in the source run and in the replay, side by side,
    with the swarms' means."""
    rows = gap["robots"]
    fig = pictures.figure(max(5.0, 0.6 * len(rows) + 2.5), 4.2)
    ax = fig.subplots()
    x = np.arange(len(rows))
    for offset, side, colour in ((-0.2, "source", "C0"), (0.2, "replay", "C3")):
        values = [np.nan if r[f"{side}_fitness"] is None else r[f"{side}_fitness"] for r in rows]
        ax.bar(x + offset, values, width=0.4, color=colour, label=f"{side}: each robot")
        mean = gap["swarm_fitness"][side]
        if mean is not None:
            ax.axhline(mean, color=colour, ls="--", lw=1, label=f"{side} swarm {mean:.3f}")
    ax.set_xticks(x, [f"{r['source_robot'] or '-'}\n{r['replay_robot'] or '-'}" for r in rows])
    ax.set_ylabel("post-evaluation fitness")
    ax.set_ylim(0, 1)
    ax.set_title(f"{title}\nreality gap: replay beside its source run")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize="small", loc="lower right")
    return pictures.save(fig, directory, "reality_gap")
