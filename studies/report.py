"""``surprise-study report``: a study's runs as tables, statistics and the paper's figures.

It never reruns anything: it reads each run's ``summary.json`` (and ``failed.json``) and the
per-evaluation files, and writes into ``DIR/report/``:

* ``runs.csv``: one row per run (group, kind, sweep values, seed, status, best fitness, final
  behaviour metrics and class, ...);
* ``evaluations.parquet``: every evolved run's evaluations (or generations), one table, with the
  run's group, seed and sweep values, for pandas users;
* ``summary.csv``: one row per group and sweep value: ``group``, ``kind``, the sweep values,
  ``runs``, ``median_fitness``, ``q1_fitness``, ``q3_fitness``, failures and behaviour counts;
* ``statistics.csv``: the paper's tests (docs/studies.md): Mann-Whitney U between evolved and
  random runs per condition (same scenario, setting and sweep values), Kruskal-Wallis across the
  conditions of one kind, Fisher's exact test on the behaviour counts of evolved against random
  per condition; p-values Bonferroni-corrected within each test's family;
* ``figures/``: best fitness over evaluations with medians (the paper's Fig. 11), rotation
  against mean cluster size with the class lines (Fig. 13), distance covered against box
  displacement with the pushing threshold (Fig. 14), mean predicted against real value per
  sensor, and the grid world's figures for grid runs; each as PNG and PDF.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from minimize_surprise.errors import ConfigError
from sim_stub import metrics as sim_metrics
from studies.runner import TASKS_FILE
from studies.stats import bonferroni, fisher, kruskal_wallis, mann_whitney
from studies.tasks import FAILED, SUMMARY, run_dir

__all__ = ["REPORT_DIR", "load_runs", "write_study_report"]

REPORT_DIR = "report"
_FIGURE_FORMATS = ("png", "pdf")
#: Up to this many values of a sweep key are also compared two by two (more: Kruskal-Wallis only,
#: as 20 grid sizes would make 190 tests).
_PAIRWISE_VALUES = 6


def _behaviour_class(behaviour: dict[str, Any] | None) -> str | None:
    if not behaviour:
        return None
    kind = f"{behaviour['motion']}/{behaviour['grouping']}"
    if behaviour.get("pushing") is not None:
        kind += "/pushing" if behaviour["pushing"] else "/not-pushing"
    return kind


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
            "post_fitness", "pattern", "quality", "size", "seconds", "host", "error",
        ):  # fmt: skip
            if key in summary:
                row[key] = summary[key]
        behaviour = summary.get("behaviour")
        if behaviour:
            for key in (
                "rotation", "mean_cluster_size", "distance_covered", "box_displacement",
                "motion", "grouping", "pushing",
            ):  # fmt: skip
                row[key] = behaviour.get(key)
            row["behaviour"] = _behaviour_class(behaviour)
        elif "pattern" in summary:
            row["behaviour"] = summary["pattern"]
        row["_summary"] = summary
        rows.append(row)
    frame = pd.DataFrame(rows)
    sweep_keys = sorted({k.split(".")[-1] for t in tasks for k in t["sweep"]})
    frame.attrs["sweep"] = sweep_keys
    return frame


def _conditions(frame) -> list[str]:
    # What makes two groups comparable: the scenario and setting (Thymio) and the sweep values.
    keys = [k for k in ("scenario", "setting") if k in frame.columns]
    return keys + [k for k in frame.attrs.get("sweep", []) if k in frame.columns]


def _summary_table(done):
    import pandas as pd

    keys = ["group", "kind", *[k for k in done.attrs.get("sweep", []) if k in done.columns]]
    rows = []
    for values, sub in done.groupby(keys, dropna=False, sort=False):
        fitness = sub["best_fitness"].astype(float)
        row = dict(zip(keys, values if isinstance(values, tuple) else (values,), strict=True))
        row.update(
            runs=len(sub),
            median_fitness=float(fitness.median()),
            q1_fitness=float(fitness.quantile(0.25)),
            q3_fitness=float(fitness.quantile(0.75)),
            min_fitness=float(fitness.min()),
            max_fitness=float(fitness.max()),
        )
        if "behaviour" in sub.columns:
            for name, count in sub["behaviour"].value_counts().items():
                row[f"n_{name}"] = int(count)
        rows.append(row)
    table = pd.DataFrame(rows)
    counts = [c for c in table.columns if c.startswith("n_")]
    table[counts] = table[counts].fillna(0).astype(int)
    return table


def _test_row(
    test: str, measure: str, condition: str, samples: str, n1: int, n2: int | None, **result
):
    return {
        "test": test, "measure": measure, "condition": condition, "samples": samples,
        "n1": n1, "n2": n2, **result,
    }  # fmt: skip


def _behaviour_table(a, b) -> tuple[list[str], list[list[int]]]:
    classes = sorted(set(a["behaviour"].dropna()) | set(b["behaviour"].dropna()))
    table = [[int((s["behaviour"] == c).sum()) for c in classes] for s in (a, b)]
    return classes, table


def _corrected(family: list[dict[str, Any]]) -> list[dict[str, Any]]:
    for row, p in zip(family, bonferroni([r["p"] for r in family]), strict=True):
        row["p_bonferroni"] = p
    return family


def _label(keys: list[str], values: Any) -> str:
    values = values if isinstance(values, tuple) else (values,)
    return ", ".join(f"{k}={v}" for k, v in zip(keys, values, strict=True)) or "all runs"


def _subsets(frame, keys: list[str]):
    # (label, rows) for every combination of the values of keys; the whole frame without keys.
    if not keys:
        yield "all runs", frame
        return
    for values, sub in frame.groupby(keys, dropna=False, sort=False):
        yield _label(keys, values), sub


def _numbers(rows, column: str) -> list[float]:
    if column not in rows.columns:
        return []
    return rows[column].dropna().astype(float).tolist()


def _two_samples(label: str, samples: str, a, b, tests: dict[str, list[dict[str, Any]]]) -> None:
    # The paper's comparison of two sets of runs: fitness and solution quality (Mann-Whitney
    # U), behaviours or patterns (Fisher's exact test on the counts).
    for column, family in (
        ("best_fitness", "mann-whitney-u"),
        ("quality", "mann-whitney-u quality"),
    ):
        x, y = _numbers(a, column), _numbers(b, column)
        if x and y:
            u = mann_whitney(x, y)
            tests[family].append(
                _test_row(
                    "mann-whitney-u",
                    column,
                    label,
                    samples,
                    len(x),
                    len(y),
                    statistic=u["U"],
                    p=u["p"],
                )
            )
    if "behaviour" in a.columns and a["behaviour"].notna().any() and b["behaviour"].notna().any():
        classes, table = _behaviour_table(a, b)
        f = fisher(table)
        tests["fisher-exact"].append(
            _test_row(
                "fisher-exact", "behaviour", label, samples, len(a), len(b),
                statistic=f.get("odds_ratio"),
                p=f["p"], classes=" ".join(classes),
            )
        )  # fmt: skip


def _statistics(done) -> list[dict[str, Any]]:
    """The paper's tests, each family Bonferroni-corrected (docs/studies.md):

    * between every two groups run under the same condition (scenario, setting, sweep values),
      e.g. evolved against random per arena or per grid size: Mann-Whitney U on the best
      fitness and on the solution quality, Fisher's exact test on the behaviours;
    * within a group across the values of one sweep key (the others fixed): Kruskal-Wallis on
      the best fitness, and Mann-Whitney U between every two values when there are at most
      :data:`_PAIRWISE_VALUES` of them (e.g. noise levels).
    """
    import itertools

    tests: dict[str, list[dict[str, Any]]] = {
        name: []
        for name in (
            "mann-whitney-u", "mann-whitney-u quality", "fisher-exact", "kruskal-wallis",
            "mann-whitney-u across",
        )
    }  # fmt: skip
    for label, sub in _subsets(done, _conditions(done)):
        groups = list(dict.fromkeys(sub["group"]))
        for a, b in itertools.combinations(groups, 2):
            rows_a, rows_b = sub[sub["group"] == a], sub[sub["group"] == b]
            _two_samples(label, f"{a} vs {b}", rows_a, rows_b, tests)
    sweep = [k for k in done.attrs.get("sweep", []) if k in done.columns]
    for group, rows in done.groupby("group", sort=False):
        for key in sweep:
            others = [k for k in sweep if k != key and rows[k].notna().any()]
            for label, sub in _subsets(rows[rows[key].notna()], others):
                where = f"{group} across {key}" + ("" if label == "all runs" else f" ({label})")
                by_value = {v: _numbers(g, "best_fitness") for v, g in sub.groupby(key)}
                by_value = {v: x for v, x in by_value.items() if x}
                if len(by_value) < 2:
                    continue
                samples = list(by_value.values())
                h = kruskal_wallis(samples)
                tests["kruskal-wallis"].append(
                    _test_row(
                        "kruskal-wallis", "best_fitness", where, f"{len(samples)} values",
                        sum(len(x) for x in samples), None, statistic=h["H"], p=h["p"],
                    )
                )  # fmt: skip
                if len(by_value) > _PAIRWISE_VALUES:
                    continue
                for (v, x), (w, y) in itertools.combinations(by_value.items(), 2):
                    u = mann_whitney(x, y)
                    tests["mann-whitney-u across"].append(
                        _test_row(
                            "mann-whitney-u", "best_fitness", where, f"{key}={v} vs {key}={w}",
                            len(x), len(y),
                            statistic=u["U"], p=u["p"],
                        )
                    )  # fmt: skip
    return [row for family in tests.values() for row in _corrected(family)]


def _evaluations_table(out: Path, done):
    import pandas as pd

    frames = []
    sweep = [k for k in done.attrs.get("sweep", []) if k in done.columns]
    for _, row in done.iterrows():
        name = row["_summary"].get("evaluations_file") or row["_summary"].get("generations_file")
        if not name:
            continue
        path = out / "runs" / row["run"] / name
        if not path.is_file():
            continue
        # The run's own "kind" column (initial, offspring, reevaluation) is the candidate's.
        table = pd.read_csv(path).rename(columns={"kind": "candidate"})
        for key in ("group", "kind", "seed", "run", *sweep):
            table.insert(0, key, row[key])
        frames.append(table)
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
    done = frame[frame["status"] == "done"].copy()
    done.attrs = frame.attrs
    summary = _summary_table(done) if len(done) else pd.DataFrame()
    summary.to_csv(target / "summary.csv", index=False)
    statistics = pd.DataFrame(_statistics(done)) if len(done) else pd.DataFrame()
    statistics.to_csv(target / "statistics.csv", index=False)
    evaluations = _evaluations_table(out, done) if len(done) else None
    if evaluations is not None:
        evaluations.to_parquet(target / "evaluations.parquet", index=False)
    figures = _figures(out, target / "figures", done, evaluations)
    return {
        "runs": len(frame),
        "done": len(done),
        "failed": int((frame["status"] == "failed").sum()),
        "groups": len(summary),
        "tests": len(statistics),
        "figures": figures,
        "report": str(target),
    }


# --------------------------------------------------------------------------- figures


def _save(fig, directory: Path, name: str) -> list[str]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for fmt in _FIGURE_FORMATS:
        path = directory / f"{name}.{fmt}"
        fig.savefig(path, dpi=150, bbox_inches="tight")
        written.append(str(path))
    return written


def _figures(out: Path, directory: Path, done, evaluations) -> list[str]:
    if not len(done):
        return []
    from matplotlib.figure import Figure

    written: list[str] = []
    thymio = done[done["kind"].isin(["evolved", "random"])]
    sweep = [k for k in done.attrs.get("sweep", []) if k in done.columns]
    # Fig. 11: best fitness over evaluations, medians and quartiles per group and sweep value.
    # (The grid world's runs count generations: its figures draw them.)
    if evaluations is not None:
        if "evaluation" in evaluations.columns:
            evaluations = evaluations[evaluations["kind"] == "evolved"]
        else:
            evaluations = None
    if evaluations is not None and len(evaluations) and "best_fitness" in evaluations.columns:
        keys = ["group", *sweep]
        labels = list(evaluations.groupby(keys, sort=False).groups)
        fig = Figure(figsize=(7, 4.2))
        ax = fig.add_subplot()
        for key in labels:
            key = key if isinstance(key, tuple) else (key,)
            mask = (evaluations[keys] == list(key)).all(axis=1)
            sub = evaluations[mask]
            by = sub.groupby("evaluation")["best_fitness"]
            median, q1, q3 = by.median(), by.quantile(0.25), by.quantile(0.75)
            label = " ".join(str(k) for k in key)
            ax.plot(median.index, median.values, label=f"{label} (median)")
            ax.fill_between(median.index, q1.values, q3.values, alpha=0.2)
        ax.set(xlabel="evaluation", ylabel="best fitness", title="Best fitness over evaluations")
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="lower right")
        written += _save(fig, directory, "fitness_over_evaluations")
    if len(thymio) and "rotation" in thymio.columns:
        # Fig. 13: rotation against mean cluster size, evolved and random, with the class lines.
        fig = Figure(figsize=(6, 4.5))
        ax = fig.add_subplot()
        for kind, marker in (("evolved", "o"), ("random", "x")):
            sub = thymio[thymio["kind"] == kind]
            if len(sub):
                ax.scatter(sub["mean_cluster_size"], sub["rotation"], marker=marker, label=kind)
        ax.axhline(sim_metrics.STOPPED_BELOW, color="grey", ls="--", lw=0.8)
        ax.axhline(sim_metrics.CIRCLING_ABOVE, color="grey", ls="--", lw=0.8)
        ax.axvline(sim_metrics.GROUPED_ABOVE, color="grey", ls=":", lw=0.8)
        ax.set(xlabel="mean cluster size", ylabel="rotation c_o (rad)",
               title="Behaviours: rotation against mean cluster size")  # fmt: skip
        ax.legend()
        written += _save(fig, directory, "rotation_vs_cluster_size")
    boxes = thymio[thymio["box_displacement"].notna()] if "box_displacement" in thymio else []
    if len(boxes):
        # Fig. 14: distance covered against box displacement, with the pushing threshold.
        fig = Figure(figsize=(6, 4.5))
        ax = fig.add_subplot()
        for kind, marker in (("evolved", "o"), ("random", "x")):
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
        sub = thymio[thymio["group"] == group]
        summaries = list(sub["_summary"])
        names = summaries[0].get("sensors") or []
        real = [s.get("mean_sensors") for s in summaries if s.get("mean_sensors")]
        pred = [s.get("mean_predictions") for s in summaries if s.get("mean_predictions")]
        ax = fig.add_subplot(len(groups), 1, i + 1)
        if not names or not real or not pred:
            continue
        idx = np.arange(len(names))
        ax.bar(idx - 0.2, np.mean(pred, axis=0), 0.4, label="predicted")
        ax.bar(idx + 0.2, np.mean(real, axis=0), 0.4, label="real")
        ax.set_xticks(idx, names, rotation=45, fontsize=7)
        ax.set(ylim=(0, 1), ylabel="mean value", title=f"{group}: mean predicted and real value")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, directory, "predicted_vs_real")
