"""A study's MAP-Elites runs beside its (1+1) runs: the behaviour classes each found and, per
class, the best elite's fitness against the runs' median best fitness (docs/quality-diversity.md).

A ``qd`` run is compared with the ``evolved`` runs of the same scenario, setting and sweep
values. A run's class is that of its best genome's post-evaluation (``tables.behaviour_class``);
an elite's is that of its own evaluation (the archive's), its post-evaluation's beside it.
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np

from studies.tables import sweep_columns

__all__ = ["TOLERANCE", "qd_comparison", "qd_markdown"]

#: How far below the runs' median best fitness of a class the best elite of that class may be
#: for the target to hold (the issue's 0.02).
TOLERANCE: Final = 0.02


def qd_comparison(done: Any) -> list[dict[str, Any]]:
    """One row per MAP-Elites run and class that it or its peer runs found (see the module
    docstring): counts, fitness figures, the difference and whether it is within
    :data:`TOLERANCE`; empty without ``qd`` runs."""
    if "kind" not in done.columns:
        return []
    keys = [k for k in ("scenario", "setting", *sweep_columns(done)) if k in done.columns]
    rows: list[dict[str, Any]] = []
    for _, qd in done[done["kind"] == "qd"].iterrows():
        peers = done[done["kind"] == "evolved"]
        for key in keys:
            peers = peers[peers[key] == qd[key]]
        runs: dict[str, list[float]] = {}
        for _, run in peers.iterrows():
            if isinstance(run.get("behaviour"), str):
                runs.setdefault(run["behaviour"], []).append(float(run["best_fitness"]))
        elites: dict[str, dict[str, Any]] = qd["_summary"].get("classes") or {}
        base = {"group": qd["group"], "seed": qd["seed"], **{k: qd[k] for k in keys}}
        for name in sorted(set(elites) | set(runs)):
            elite = elites.get(name) or {}
            fitness = runs.get(name, [])
            median = float(np.median(fitness)) if fitness else None
            best = elite.get("fitness")
            difference = None if best is None or median is None else best - median
            rows.append(
                base
                | {
                    "class": name,
                    "qd_elite_fitness": best,
                    "qd_post_fitness": elite.get("post_fitness"),
                    "qd_post_class": elite.get("post_class"),
                    "runs": len(fitness),
                    "runs_median_best_fitness": median,
                    "difference": difference,
                    "within_tolerance": None if difference is None else _within(difference),
                }
            )
    return rows


def qd_markdown(rows: list[dict[str, Any]]) -> str:
    """The comparison as Markdown: per MAP-Elites run, the classes each side found, the
    per-class table and whether the targets hold."""
    out: list[str] = []
    runs = sorted({(r["group"], r["seed"]) for r in rows})
    for group, seed in runs:
        mine = [r for r in rows if (r["group"], r["seed"]) == (group, seed)]
        qd_classes = [r["class"] for r in mine if r["qd_elite_fitness"] is not None]
        run_classes = [r["class"] for r in mine if r["runs"]]
        both = [r for r in mine if r["difference"] is not None]
        worst = min((r["difference"] for r in both), default=None)
        out += [
            f"## {group}, seed {seed}",
            "",
            f"- classes in the archive: {len(qd_classes)} ({', '.join(qd_classes) or 'none'})",
            f"- classes of the runs' best genomes: {len(run_classes)} "
            f"({', '.join(run_classes) or 'none'})",
            f"- more classes than the runs: {_yes(len(qd_classes) > len(run_classes))}",
            f"- every shared class within {TOLERANCE} of the runs' median: "
            + ("n/a" if worst is None else f"{_yes(_within(worst))} (worst {worst:+.4f})"),
            "",
            "| class | elite fitness | elite post-evaluated | runs | runs' median best | "
            "difference |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for r in mine:
            post = r["qd_post_fitness"]
            out.append(
                f"| {r['class']} | {_num(r['qd_elite_fitness'])} | "
                + ("-" if post is None else f"{post:.4f} ({r['qd_post_class']})")
                + f" | {r['runs']} | {_num(r['runs_median_best_fitness'])} | "
                + ("-" if r["difference"] is None else f"{r['difference']:+.4f}")
                + " |"
            )
        out.append("")
    return "\n".join(out)


def _within(difference: float) -> bool:
    # Rounded first: 0.90 - 0.92 is -0.0200000000000000018 in binary, and at the bound.
    return round(difference, 9) >= -TOLERANCE


def _yes(value: bool) -> str:
    return "yes" if value else "no"


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"
