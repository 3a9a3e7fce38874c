"""What the robots themselves reported over a run: late control steps, failed sensor reads and
their batteries, from the per-robot columns of ``evaluations.csv`` (docs/runs.md)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from minimize_surprise.text import plural

__all__ = ["parse_robot_stats", "robot_lines", "robot_stats"]


def parse_robot_stats(
    row: Mapping[str, str], robots: Sequence[str]
) -> dict[str, tuple[float | None, int, int]] | None:
    """One row's ``(battery_v, overruns, read_failures)`` per robot; None for a file without
    these columns (the compiled engine, runs written before them). A robot not in the row's
    swarm (it left, or joined later: empty cells) is not in it."""
    if not robots or f"overruns_{robots[0]}" not in row:
        return None
    parsed = {}
    for robot in robots:
        if not row.get(f"overruns_{robot}"):
            continue
        battery = row.get(f"battery_v_{robot}") or ""
        parsed[robot] = (
            float(battery) if battery else None,
            int(row[f"overruns_{robot}"]),
            int(row[f"read_failures_{robot}"]),
        )
    return parsed


def robot_stats(rows: Sequence[Mapping[str, Any]], robots: Sequence[str]) -> dict[str, Any] | None:
    """Per robot over the run: late steps and failed reads (totals, and in how many evaluations),
    and the battery's first, lowest and last reading (None where unknown)."""
    stats = [row["robot_stats"] for row in rows if row.get("robot_stats") is not None]
    if not stats:
        return None
    summary: dict[str, Any] = {}
    for robot in robots:
        # Only the rows of the swarms the robot was in (it may have left or joined).
        stats_of = [s for s in stats if robot in s]
        if not stats_of:
            continue
        batteries = [s[robot][0] for s in stats_of if s[robot][0] is not None]
        summary[robot] = {
            "overruns": sum(s[robot][1] for s in stats_of),
            "evaluations_with_overruns": sum(s[robot][1] > 0 for s in stats_of),
            "read_failures": sum(s[robot][2] for s in stats_of),
            "evaluations_with_read_failures": sum(s[robot][2] > 0 for s in stats_of),
            "battery_first_v": batteries[0] if batteries else None,
            "battery_min_v": min(batteries) if batteries else None,
            "battery_last_v": batteries[-1] if batteries else None,
        }
    return summary


def robot_lines(summary: Mapping[str, Any] | None) -> list[str]:
    """Lines for a person: robots that ran late or failed to read, and the batteries."""
    if not summary:
        return []
    lines = []
    for robot, s in summary.items():
        parts = []
        if s["overruns"]:
            parts.append(
                f"{plural(s['overruns'], 'late control step')} in "
                f"{plural(s['evaluations_with_overruns'], 'evaluation')}"
            )
        if s["read_failures"]:
            parts.append(
                f"{plural(s['read_failures'], 'failed sensor read')} in "
                f"{plural(s['evaluations_with_read_failures'], 'evaluation')}"
            )
        if parts:
            lines.append(f"robot {robot}: " + ", ".join(parts))
    batteries = [
        f"{robot} {s['battery_first_v']:.2f} -> {s['battery_last_v']:.2f} V "
        f"(lowest {s['battery_min_v']:.2f})"
        for robot, s in summary.items()
        if s["battery_first_v"] is not None
    ]
    if batteries:
        lines.append("batteries: " + ", ".join(batteries))
    return lines
