"""``surprise-study report``: a study's runs as tables, statistics and the paper's figures.

It never reruns anything: it reads each run's ``summary.json`` (and ``failed.json``) and the
per-evaluation files, a recorded run's afresh from its own directory (:mod:`studies.recorded`),
and writes into ``DIR/report/``:

* ``runs.csv``: one row per run (group, kind, sweep values, seed, status, best fitness, final
  behaviour metrics and class, ...);
* ``evaluations.parquet``: every evolved run's evaluations (or generations), one table, with the
  run's group, seed and sweep values, for pandas users;
* ``summary.csv``: one row per group and sweep value: ``group``, ``kind``, the sweep values,
  ``runs``, ``median_fitness``, ``q1_fitness``, ``q3_fitness``, failures and behaviour counts;
* ``paper.csv`` and ``paper.md``: where the study file says what the paper reports for a group
  (its ``paper`` section), each condition's median best fitness and behaviour classes beside the
  paper's bound and classes;
* ``statistics.csv``: the paper's tests (docs/studies.md): Mann-Whitney U between evolved and
  random runs per condition (same scenario, setting and sweep values), Kruskal-Wallis across the
  conditions of one kind, Fisher's exact test on the behaviour counts of evolved against random
  per condition; p-values Bonferroni-corrected within each test's family;
* ``clusters.csv`` and ``clusters.md``: the behaviours clustered without the hand thresholds
  (:mod:`studies.clusters`: standardised metrics or pattern scores, PCA, HDBSCAN) and their
  agreement with the hand-set classes (adjusted Rand index), per family (arena, grid world);
* ``qd.csv`` and ``qd.md``: with ``qd`` (MAP-Elites) runs, the classes each MAP-Elites run and
  its peer evolved runs found and, per class, the best elite's fitness against the runs' median
  best fitness (:mod:`studies.qd_tables`);
* ``recovery.csv`` and ``recovery.md``: for runs whose arena changes, per group and change the
  median drop of fitness and evaluations to recover across seeds (:mod:`studies.recovery`);
* ``problems.txt``: one line per run left out (failed; a recorded run missing, unfinished or
  unreadable), naming it and why;
* ``figures/``: best fitness over evaluations with medians (the paper's Fig. 11; recorded groups
  dashed, "real robots" in the legend), rotation
  against mean cluster size with the class lines (Fig. 13), distance covered against box
  displacement with the pushing threshold (Fig. 14), mean predicted against real value per
  sensor, the grid world's figures for grid runs, and ``clusters-<family>``: the runs in the
  projection coloured by cluster and by hand-set class; each as PNG and PDF.

This module reads and writes; the tables, the tests and what the figures draw are computed from
the runs' frame by :mod:`studies.tables`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec

from minimize_surprise.errors import ConfigError
from minimize_surprise.figures import save_figure
from simulator import metrics as sim_metrics
from studies import tables
from studies.clusters import (
    Clustering,
    cluster_behaviours,
    clusters_figure,
    clusters_markdown,
    clusters_table,
)
from studies.qd_tables import qd_comparison, qd_markdown
from studies.recorded import RECORDED, refreshed
from studies.recovery import recovery_markdown, recovery_rows
from studies.runner import STUDY_FILE, TASKS_FILE
from studies.spec import load_study
from studies.tasks import FAILED, SUMMARY, run_dir

__all__ = ["PROBLEMS", "REPORT_DIR", "load_runs", "write_study_report"]

REPORT_DIR = "report"
#: In the report's directory: one line per run left out, and why (none: no file).
PROBLEMS = "problems.txt"


def load_runs(out: str | Path):
    """Every run of the study in ``out`` as one row of a pandas DataFrame (not run yet: left
    out; failed: ``status`` "failed" with the error)."""
    import pandas as pd

    out = Path(out)
    tasks_file = out / TASKS_FILE
    if not tasks_file.is_file():
        raise ConfigError(f"{out} is not a study directory: {TASKS_FILE} is missing")
    tasks = json.loads(tasks_file.read_text(encoding="utf-8"))
    rows = []
    for task in tasks:
        directory = run_dir(out, task)
        summary = None
        for name in (SUMMARY, FAILED):
            path = directory / name
            if path.is_file():
                summary = json.loads(path.read_text(encoding="utf-8"))
                break
        if summary is None:
            continue
        if task["kind"] == RECORDED:  # read where it is: it may have gained a class since
            summary = refreshed(task, summary)
        row: dict[str, Any] = {
            "group": task["group"],
            "kind": task["kind"],
            "seed": task["seed"],
            "run": task["run"],
            "status": summary.get("status"),
        }
        for key, value in task["sweep"].items():
            row[key.split(".")[-1]] = value
        for key in (
            "scenario", "setting", "robots", "evaluations", "best_fitness", "fitness",
            "post_fitness", "pattern", "quality", "size", "safety_share",
            "evolution_safety_share", "real", "source", "behaviour_missing", "seconds", "batch",
            "host", "error",
        ):  # fmt: skip
            if key in summary:
                row[key] = summary[key]
        behaviour = summary.get("behaviour")
        if behaviour:
            for key in (
                "rotation", "mean_cluster_size", "distance_covered", "box_displacement",
                "motion", "grouping", "pushing", "backward_share", "manipulation", "turn_rate",
                "still_share", "neighbour_distance",
            ):  # fmt: skip
                row[key] = behaviour.get(key)
            row["behaviour"] = tables.behaviour_class(behaviour)
        elif "pattern" in summary:
            row["behaviour"] = summary["pattern"]
        elif summary.get("behaviour_missing"):
            row["behaviour"] = tables.UNKNOWN
        row["_summary"] = summary
        rows.append(row)
    frame = pd.DataFrame(rows)
    sweep_keys = sorted({k.split(".")[-1] for t in tasks for k in t["sweep"]})
    frame.attrs["sweep"] = sweep_keys
    return frame


def _evaluations_table(out: Path, done):
    import pandas as pd

    frames = []
    sweep = tables.sweep_columns(done)
    for _, row in done.iterrows():
        name = row["_summary"].get("evaluations_file") or row["_summary"].get("generations_file")
        if not name:
            continue
        path = out / "runs" / row["run"] / name  # a recorded run's is absolute: its own
        if not path.is_file():
            continue
        # The run's own "kind" column (initial, offspring, reevaluation) is the candidate's.
        table = pd.read_csv(path).rename(columns={"kind": "candidate"})
        # The run's identity first (one concat: a swarm of a thousand has thousands of columns,
        # which inserting one by one would copy each time).
        keys = list(reversed(("group", "kind", "seed", "run", *sweep)))
        ids = pd.DataFrame({key: row[key] for key in keys}, index=table.index)
        frames.append(pd.concat([ids, table], axis=1))
    if not frames:
        return None
    return pd.concat(frames, ignore_index=True)


def write_study_report(out: str | Path) -> dict[str, Any]:
    """Write the report of the study in ``out`` (see the module docstring); what it found."""
    import pandas as pd

    out = Path(out)
    frame = load_runs(out)
    target = out / REPORT_DIR
    target.mkdir(exist_ok=True)
    if frame.empty:
        raise ConfigError(f"{out}: no run has finished yet")
    public = frame.drop(columns=["_summary"])
    public.to_csv(target / "runs.csv", index=False)
    problems = _problems(frame)
    (target / PROBLEMS).unlink(missing_ok=True)  # an earlier report's
    if problems:
        (target / PROBLEMS).write_text("".join(f"{line}\n" for line in problems), "utf-8")
    done = frame[frame["status"] == "done"].copy()
    done.attrs = frame.attrs
    summary = tables.summary_table(done) if len(done) else pd.DataFrame()
    summary.to_csv(target / "summary.csv", index=False)
    papers = _paper_sections(out)
    if papers and len(summary):
        beside = tables.paper_table(summary, papers)
        beside.to_csv(target / "paper.csv", index=False)
        (target / "paper.md").write_text(_markdown(beside), encoding="utf-8")
    tests = pd.DataFrame(tables.statistics(done)) if len(done) else pd.DataFrame()
    tests.to_csv(target / "statistics.csv", index=False)
    qd_rows = qd_comparison(done) if len(done) else []
    if qd_rows:
        pd.DataFrame(qd_rows).to_csv(target / "qd.csv", index=False)
        (target / "qd.md").write_text(qd_markdown(qd_rows), encoding="utf-8")
    evaluations = _evaluations_table(out, done) if len(done) else None
    if evaluations is not None:
        evaluations.to_parquet(target / "evaluations.parquet", index=False)
    figures = _figures(out, target / "figures", done, evaluations)
    changes = recovery_rows(done) if len(done) else []
    if changes:  # the runs' arena changed (docs/changing-arenas.md)
        pd.DataFrame(changes).to_csv(target / "recovery.csv", index=False)
        (target / "recovery.md").write_text(recovery_markdown(changes), encoding="utf-8")
    found = _clusters(target, done) if len(done) else []
    figures += [f for c in found if not c.note for f in _save(
        clusters_figure(c), target / "figures", f"clusters-{c.family}"
    )]  # fmt: skip
    return {
        "runs": len(frame),
        "done": len(done),
        "failed": int((frame["status"] == "failed").sum()),
        "groups": len(summary),
        "tests": len(tests),
        "figures": figures,
        "problems": problems,
        "clusters": {c.family: {"clusters": c.clusters, "ari": c.ari} for c in found},
        "recovery": changes,
        "report": str(target),
        "qd": len(qd_rows),
    }


def _clusters(target: Path, done: Any) -> list[Clustering]:
    # Classes found by the data beside the hand-set ones (studies.clusters).
    found = cluster_behaviours(done)
    if found:
        clusters_table(found).to_csv(target / "clusters.csv", index=False)
        (target / "clusters.md").write_text(clusters_markdown(found) + "\n", encoding="utf-8")
    return found


def _problems(frame) -> list[str]:
    """One line per run the report leaves out, naming it and why: a run that failed, a recorded
    run that is missing, unfinished or unreadable (its error names the directory)."""
    failed = frame[frame["status"] != "done"]
    if "error" not in failed.columns:
        return [f"{row['run']}: failed" for _, row in failed.iterrows()]
    return [f"{row['run']}: {row['error']}" for _, row in failed.iterrows()]


def _paper_sections(out: Path) -> dict[str, dict[str, Any]]:
    """Each group's ``paper`` section of the study file the study was run with."""
    path = out / STUDY_FILE
    if not path.is_file():
        return {}
    study = load_study(path)
    return {g.name: msgspec.to_builtins(g.paper) for g in study.groups if g.paper is not None}


def _markdown(table: Any) -> str:
    """A table as Markdown, for docs/ (pandas' own needs the tabulate package)."""
    header = list(table.columns)
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for _, row in table.iterrows():
        cells = ["" if v is None or v != v else str(v) for v in row.tolist()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- figures


def _save(fig, directory: Path, name: str) -> list[str]:
    directory.mkdir(parents=True, exist_ok=True)
    return [str(path) for path in save_figure(fig, directory / name)]


#: The scatter figures' marker per kind (recorded: the lab's runs, most often real).
_MARKERS = (("evolved", "o"), ("random", "x"), (RECORDED, "s"))


def _group_words(done) -> dict[str, tuple[str, str]]:
    """Per group, what its fitness curve's legend says it is and its line's style: recorded
    groups dashed, "real robots" when every run of them ran on robots (no simulation.json)."""
    words = {}
    for group, rows in done.groupby("group", sort=False):
        if (rows["kind"] != RECORDED).any():
            continue
        real = "real" in rows.columns and rows["real"].fillna(False).astype(bool).all()
        words[str(group)] = ("real robots" if real else "recorded", "--")
    return words


def _figures(out: Path, directory: Path, done, evaluations) -> list[str]:
    if not len(done):
        return []
    from matplotlib.figure import Figure

    written: list[str] = []
    thymio = done[done["kind"].isin(["evolved", "random", RECORDED])]
    sweep = tables.sweep_columns(done)
    # Fig. 11: best fitness over evaluations, medians and quartiles per group and sweep value,
    # recorded (real) groups beside simulated ones. (The grid world's runs count generations:
    # its figures draw them.)
    if evaluations is not None:
        if "evaluation" in evaluations.columns:
            evaluations = evaluations[evaluations["kind"].isin(["evolved", RECORDED])]
        else:
            evaluations = None
    if evaluations is not None and len(evaluations) and "best_fitness" in evaluations.columns:
        fig = Figure(figsize=(7, 4.2))
        ax = fig.add_subplot()
        what = _group_words(done)
        for key, label, median, q1, q3 in tables.fitness_curves(evaluations, ["group", *sweep]):
            words, style = what.get(key[0], ("simulated", "-"))
            (line,) = ax.plot(
                median.index, median.values, ls=style, label=f"{label} ({words}, median)"
            )
            ax.fill_between(median.index, q1.values, q3.values, alpha=0.2, color=line.get_color())
        ax.set(xlabel="evaluation", ylabel="best fitness", title="Best fitness over evaluations")
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="lower right")
        written += _save(fig, directory, "fitness_over_evaluations")
    if len(thymio) and "rotation" in thymio.columns:
        # Fig. 13: rotation against mean cluster size, evolved and random, with the class lines.
        fig = Figure(figsize=(6, 4.5))
        ax = fig.add_subplot()
        for kind, marker in _MARKERS:
            sub = thymio[thymio["kind"] == kind]
            if len(sub) and sub["rotation"].notna().any():
                ax.scatter(sub["mean_cluster_size"], sub["rotation"], marker=marker, label=kind)
        ax.axhline(sim_metrics.STOPPED_BELOW, color="grey", ls="--", lw=0.8)
        ax.axhline(sim_metrics.CIRCLING_ABOVE, color="grey", ls="--", lw=0.8)
        ax.axvline(sim_metrics.GROUPED_ABOVE, color="grey", ls=":", lw=0.8)
        ax.set(xlabel="mean cluster size", ylabel="rotation c_o (rad)",
               title="Behaviours: rotation against mean cluster size")  # fmt: skip
        ax.legend()
        written += _save(fig, directory, "rotation_vs_cluster_size")
    boxes = thymio[thymio["box_displacement"].notna()] if "box_displacement" in thymio else None
    if boxes is not None and len(boxes):
        # Fig. 14: distance covered against box displacement, with the pushing threshold.
        fig = Figure(figsize=(6, 4.5))
        ax = fig.add_subplot()
        for kind, marker in _MARKERS:
            sub = boxes[boxes["kind"] == kind]
            if len(sub):
                ax.scatter(
                    sub["distance_covered"], sub["box_displacement"], marker=marker, label=kind
                )
        ax.axhline(sim_metrics.PUSHING_ABOVE, color="grey", ls="--", lw=0.8)
        ax.set(xlabel="distance covered d_R (m)", ylabel="box displacement d_B (m)",
               title="Object manipulation: d_R against d_B")  # fmt: skip
        ax.legend()
        written += _save(fig, directory, "distance_vs_box_displacement")
    if len(thymio):
        written += _prediction_figure(thymio, directory)
    grid = done[done["kind"].str.startswith("grid-")]
    if len(grid):
        try:
            from gridworld import figures as grid_figures
        except ImportError:
            pass
        else:
            written += grid_figures.study_figures(out, grid, directory)
    return written


def _prediction_figure(thymio, directory: Path) -> list[str]:
    import numpy as np
    from matplotlib.figure import Figure

    groups = [g for g, sub in thymio.groupby("group", sort=False)]
    fig = Figure(figsize=(7, 2.6 * len(groups)))
    for i, group in enumerate(groups):
        means = tables.mean_sensor_values(thymio[thymio["group"] == group])
        ax = fig.add_subplot(len(groups), 1, i + 1)
        if means is None:
            continue
        names, predicted, real = means
        idx = np.arange(len(names))
        ax.bar(idx - 0.2, predicted, 0.4, label="predicted")
        ax.bar(idx + 0.2, real, 0.4, label="real")
        ax.set_xticks(idx, names, rotation=45, fontsize=7)
        ax.set(ylim=(0, 1), ylabel="mean value", title=f"{group}: mean predicted and real value")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, directory, "predicted_vs_real")
