"""Fitness around each change of the arena: how far it drops and how long it takes to recover
(docs/changing-arenas.md).

For every ``arena-change`` and ``mark`` line of ``events.jsonl`` (each names the counted
evaluations done before it, ``e``), with the run's fitness per evaluation ``f``:

* **level before**: the median of the ``window`` evaluations before, ``f[e - window + 1 .. e]``;
* **drop**: that level minus the lowest fitness of the ``window`` evaluations after,
  ``f[e + 1 .. e + window]`` (negative: the change made the task easier);
* **recovery**: the evaluations after the change until the median of the last ``window``
  evaluations, all of them after the change, is back at the level before: ``k`` for the first
  ``k >= window`` with ``median(f[e + k - window + 1 .. e + k]) >= level``; None: not recovered
  within the run. By construction it is at least ``window``.

An event with fewer than ``window`` evaluations on either side still gets a level or a drop from
what there is (at least one), and no recovery without a whole window after it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import msgspec
import numpy as np

from reporting import pictures
from runfiles.schema import EVENT_ARENA, EVENT_MARK, Event

__all__ = [
    "WINDOW",
    "Recovery",
    "recoveries",
    "recovery_metrics",
    "recovery_picture",
    "recovery_table",
]

#: Evaluations a level is the median of (before the change, and the moving median after).
WINDOW: Final = 10


class Recovery(msgspec.Struct, frozen=True, kw_only=True):
    """Fitness around one change (see the module docstring)."""

    #: ``arena-change`` (the experiment's event) or ``mark`` (a person's)
    kind: str
    #: what changed
    detail: str
    #: counted evaluations before the change
    evaluation: int
    level_before: float | None
    lowest_after: float | None
    drop: float | None
    #: evaluations after the change until the moving median is back; None: not recovered
    recovery: int | None


def recoveries(
    fitness: Sequence[float], events: Sequence[Event], *, window: int = WINDOW
) -> list[Recovery]:
    """Drop and recovery around every arena change and mark of ``events`` in the series
    ``fitness`` (the fitness of counted evaluations 1, 2, ...), in the events' order."""
    f = np.asarray(fitness, dtype=float)
    out = []
    for event in events:
        if event.kind not in (EVENT_ARENA, EVENT_MARK) or event.evaluation is None:
            continue
        e = event.evaluation
        before, after = f[max(0, e - window) : e], f[e : e + window]
        level = float(np.median(before)) if len(before) else None
        lowest = float(after.min()) if len(after) else None
        drop = None if level is None or lowest is None else level - lowest
        recovery = None
        if level is not None:
            for k in range(window, len(f) - e + 1):
                if np.median(f[e + k - window : e + k]) >= level:
                    recovery = k
                    break
        out.append(
            Recovery(
                kind=event.kind,
                detail=event.detail,
                evaluation=e,
                level_before=level,
                lowest_after=lowest,
                drop=drop,
                recovery=recovery,
            )
        )
    return out


def recovery_table(found: Sequence[Recovery]) -> str:
    """The changes as a Markdown table (the report's text)."""
    lines = [
        "| after evaluation | change | level before | lowest after | drop | recovered after |",
        "| ---: | --- | ---: | ---: | ---: | --- |",
    ]
    for r in found:
        back = "not recovered" if r.recovery is None else f"{r.recovery} evaluations"
        lines.append(
            f"| {r.evaluation} | {r.detail}{' (mark)' if r.kind == EVENT_MARK else ''} | "
            f"{_f(r.level_before)} | {_f(r.lowest_after)} | {_f(r.drop)} | {back} |"
        )
    return "\n".join(lines) + "\n"


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def recovery_picture(
    directory: Path,
    fitness: Sequence[float],
    found: Sequence[Recovery],
    title: str,
    *,
    window: int = WINDOW,
) -> list[Path]:
    """``plots/recovery``: the fitness per evaluation, its moving median, each change as a
    vertical line with the level before it and where the median is back; the files written."""
    f = np.asarray(fitness, dtype=float)
    x = np.arange(1, len(f) + 1)
    fig = pictures.figure(8, 4)
    ax = fig.add_subplot()
    ax.plot(x, f, ".", color="0.65", markersize=3, label="fitness")
    if len(f) >= window:
        median = [np.median(f[i - window : i]) for i in range(window, len(f) + 1)]
        ax.plot(x[window - 1 :], median, color="C0", label=f"median of {window}")
    for r in found:
        colour = "C3" if r.kind == EVENT_ARENA else "C2"
        ax.axvline(r.evaluation + 0.5, color=colour, linestyle="--", linewidth=1)
        ax.annotate(
            r.detail, (r.evaluation + 0.5, 1.0), xycoords=("data", "axes fraction"),
            rotation=90, va="top", ha="right", fontsize=7, color=colour,
        )  # fmt: skip
        if r.level_before is not None:
            end = r.evaluation + (r.recovery or len(f) - r.evaluation)
            ax.hlines(r.level_before, max(1, r.evaluation - window + 1), end, color=colour)
        if r.recovery is not None and r.level_before is not None:
            ax.plot([r.evaluation + r.recovery], [r.level_before], "o", color=colour)
    ax.set_xlabel("evaluation")
    ax.set_ylabel("swarm fitness")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    return pictures.save(fig, directory, "recovery")


def recovery_metrics(found: Sequence[Recovery]) -> list[dict[str, Any]]:
    """The changes as ``metrics.json`` holds them."""
    return [msgspec.to_builtins(r) for r in found]
