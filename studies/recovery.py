"""Recovery across seeds: for a study whose runs' arena changes, how far fitness drops at each
change and how many evaluations it takes to recover, per group and change (docs/
changing-arenas.md). Each run's summary holds its report's ``recovery`` list
(:mod:`reporting.recovery`); the changes of one group line up by their position in it.
"""

from __future__ import annotations

import statistics
from typing import Any

__all__ = ["recovery_markdown", "recovery_rows"]


def recovery_rows(done: Any) -> list[dict[str, Any]]:
    """One row per group and change: the runs that had it, the median level before, drop and
    recovery (over the runs that recovered), and how many recovered."""
    found: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for _, row in done.iterrows():
        for position, change in enumerate(row["_summary"].get("recovery") or []):
            found.setdefault((row["group"], position), []).append(change)
    out = []
    for (group, position), changes in sorted(found.items()):
        drops = [c["drop"] for c in changes if c["drop"] is not None]
        levels = [c["level_before"] for c in changes if c["level_before"] is not None]
        back = [c["recovery"] for c in changes if c["recovery"] is not None]
        out.append(
            {
                "group": group,
                "change": position,
                "detail": changes[0]["detail"],
                "evaluation": changes[0]["evaluation"],
                "runs": len(changes),
                "median_level_before": statistics.median(levels) if levels else None,
                "median_drop": statistics.median(drops) if drops else None,
                "min_drop": min(drops) if drops else None,
                "max_drop": max(drops) if drops else None,
                "recovered": len(back),
                "median_recovery": statistics.median(back) if back else None,
            }
        )
    return out


def recovery_markdown(rows: list[dict[str, Any]]) -> str:
    """The rows as a Markdown table (``report/recovery.md``)."""
    lines = [
        "| group | after evaluation | change | runs | level before | drop (median, range) | "
        "recovered | recovery (median evaluations) |",
        "| --- | ---: | --- | ---: | ---: | --- | ---: | ---: |",
    ]
    for r in rows:
        drop = (
            "-"
            if r["median_drop"] is None
            else f"{r['median_drop']:.4f} ({r['min_drop']:.4f} to {r['max_drop']:.4f})"
        )
        level = "-" if r["median_level_before"] is None else f"{r['median_level_before']:.4f}"
        back = "-" if r["median_recovery"] is None else f"{r['median_recovery']:g}"
        lines.append(
            f"| {r['group']} | {r['evaluation']} | {r['detail']} | {r['runs']} | {level} | "
            f"{drop} | {r['recovered']}/{r['runs']} | {back} |"
        )
    return "\n".join(lines) + "\n"
