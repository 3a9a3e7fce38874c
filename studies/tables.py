"""A study's tables and statistics, computed from pandas frames; no file is read or written here.

:mod:`studies.report` reads the runs (:func:`studies.report.load_runs`: one row per run, the
sweep keys in ``frame.attrs["sweep"]``), calls these functions on the finished ones, and writes
what they return:

* :func:`behaviour_class`: a run's behaviour as one label (``circling/grouped/pushing``; a run
  without one, e.g. a real run without a tracker's positions, is :data:`UNKNOWN`);
* :func:`summary_table`: one row per group and sweep value with the fitness's median, quartiles
  and range, and the count of each behaviour;
* :func:`statistics`: the paper's tests (docs/studies.md, on top of :mod:`studies.stats`), each
  family Bonferroni-corrected;
* :func:`fitness_curves` and :func:`mean_sensor_values`: what the report's figures draw.

pandas (the ``studies`` extra) is imported inside the functions that build a frame.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Any

import numpy as np

from simulator.metrics import classify_manipulation
from studies.stats import bonferroni, fisher, kruskal_wallis, mann_whitney

__all__ = [
    "PAIRWISE_VALUES",
    "UNKNOWN",
    "behaviour_class",
    "conditions",
    "fitness_curves",
    "mean_sensor_values",
    "statistics",
    "summary_table",
    "sweep_columns",
]

#: The class of a run whose behaviour is not known (a real run without a tracker's positions):
#: counted in the tables, left out of the tests on the classes.
UNKNOWN = "unknown"

#: Up to this many values of a sweep key are also compared two by two (more: Kruskal-Wallis only,
#: as 20 grid sizes would make 190 tests).
PAIRWISE_VALUES = 6


def behaviour_class(behaviour: dict[str, Any] | None) -> str | None:
    """A run's behaviour class: with boxes the paper's object-manipulation class (``pushing``,
    ``reverse driving`` or ``circling``, simulator.metrics.classify_manipulation), else
    ``motion/grouping``; None without behaviour."""
    if not behaviour:
        return None
    backward, d_b = behaviour.get("backward_share"), behaviour.get("box_displacement")
    if backward is not None and d_b is not None:
        # From the metrics, by the current rule, whatever rule the run was classed by.
        return classify_manipulation(d_b, backward, behaviour["motion"])
    kind = f"{behaviour['motion']}/{behaviour['grouping']}"
    if behaviour.get("pushing") is not None:  # metrics written before the classes existed
        kind += "/pushing" if behaviour["pushing"] else "/not-pushing"
    return kind


def sweep_columns(frame: Any) -> list[str]:
    """The study's sweep keys that are columns of ``frame``."""
    return [k for k in frame.attrs.get("sweep", []) if k in frame.columns]


def conditions(frame: Any) -> list[str]:
    """The columns that make two groups' runs comparable: the scenario and setting (Thymio) and
    the sweep values."""
    keys = [k for k in ("scenario", "setting") if k in frame.columns]
    return keys + sweep_columns(frame)


def summary_table(done: Any) -> Any:
    """One row per group and sweep value of the finished runs ``done``: ``group``, ``kind``, the
    sweep values, ``runs``, the best fitness's median, quartiles, minimum and maximum, and
    ``n_<behaviour>`` counts."""
    import pandas as pd

    keys = ["group", "kind", *sweep_columns(done)]
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


def paper_table(summary: Any, papers: dict[str, dict[str, Any]]) -> Any:
    """The rows of ``summary`` (:func:`summary_table`) whose group the study file says the paper
    reported on (``papers``: group name to its ``paper`` section), each beside the paper: its
    bound on the median best fitness, whether ours holds it, our behaviour classes with their
    counts, and the paper's classes in its words."""
    import pandas as pd

    rows = []
    counts = [c for c in summary.columns if c.startswith("n_")]
    sweep = [c for c in summary.columns if c not in {"group", "kind", "runs"}
             and not c.endswith("_fitness") and not c.startswith("n_")]  # fmt: skip
    for _, row in summary.iterrows():
        paper = papers.get(row["group"])
        if paper is None:
            continue
        median = float(row["median_fitness"])
        low, high = paper.get("median_fitness_at_least"), paper.get("median_fitness_at_most")
        bound = " and ".join(
            text for text in (
                None if low is None else f">= {low:g}", None if high is None else f"<= {high:g}"
            ) if text
        )  # fmt: skip
        holds = (low is None or median >= low) and (high is None or median <= high)
        classes = sorted(((int(row[c]), c[2:]) for c in counts if row[c]), reverse=True)
        rows.append(
            {
                "group": row["group"],
                # Other groups' sweep keys are empty (NaN) in this group's rows.
                "condition": ", ".join(f"{k}={row[k]}" for k in sweep if row[k] == row[k]),
                "runs": int(row["runs"]),
                "median_fitness": round(median, 4),
                "paper_median_fitness": bound,
                "holds": bool(holds) if bound else None,
                "classes": ", ".join(f"{name} {n}" for n, name in classes),
                "paper_classes": paper.get("classes", ""),
                "source": paper.get("source", ""),
            }
        )
    return pd.DataFrame(rows)


# --------------------------------------------------------------------------- the tests


def _test_row(
    test: str, measure: str, condition: str, samples: str, n1: int, n2: int | None, **result: Any
) -> dict[str, Any]:
    return {
        "test": test, "measure": measure, "condition": condition, "samples": samples,
        "n1": n1, "n2": n2, **result,
    }  # fmt: skip


def _known(rows: Any) -> Any:
    """The classes of ``rows`` that are known (not missing, not :data:`UNKNOWN`)."""
    classes = rows["behaviour"].dropna()
    return classes[classes != UNKNOWN]


def _one_scheme(a: Any, b: Any) -> bool:
    """Whether the classes ``a`` and ``b`` (both some) are of one kind, so that counting them
    against each other means something: motion and grouping (``circling/dispersed``: a basic
    run, or a real run among boxes whose boxes no tracker followed), or one label each (the
    object-manipulation classes, the grid world's patterns)."""
    kinds = {"/" in str(c) for c in (*a, *b)}
    return len(b) > 0 and len(kinds) == 1


def _behaviour_table(a: Any, b: Any) -> tuple[list[str], list[list[int]]]:
    classes = sorted(set(_known(a)) | set(_known(b)))
    table = [[int((s["behaviour"] == c).sum()) for c in classes] for s in (a, b)]
    return classes, table


def _corrected(family: list[dict[str, Any]]) -> list[dict[str, Any]]:
    for row, p in zip(family, bonferroni([r["p"] for r in family]), strict=True):
        row["p_bonferroni"] = p
    return family


def _label(keys: list[str], values: Any) -> str:
    values = values if isinstance(values, tuple) else (values,)
    return ", ".join(f"{k}={v}" for k, v in zip(keys, values, strict=True)) or "all runs"


def _subsets(frame: Any, keys: list[str]) -> Iterator[tuple[str, Any]]:
    # (label, rows) for every combination of the values of keys; the whole frame without keys.
    if not keys:
        yield "all runs", frame
        return
    for values, sub in frame.groupby(keys, dropna=False, sort=False):
        yield _label(keys, values), sub


def _numbers(rows: Any, column: str) -> list[float]:
    if column not in rows.columns:
        return []
    return rows[column].dropna().astype(float).tolist()


def _two_samples(
    label: str, samples: str, a: Any, b: Any, tests: dict[str, list[dict[str, Any]]]
) -> None:
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
    if "behaviour" in a.columns and len(_known(a)) and _one_scheme(_known(a), _known(b)):
        classes, table = _behaviour_table(a, b)
        f = fisher(table)
        tests["fisher-exact"].append(
            _test_row(
                "fisher-exact", "behaviour", label, samples, len(_known(a)), len(_known(b)),
                statistic=f.get("odds_ratio"),
                p=f["p"], classes=" ".join(classes),
            )
        )  # fmt: skip


def statistics(done: Any) -> list[dict[str, Any]]:
    """The paper's tests on the finished runs ``done``, one row each, each family
    Bonferroni-corrected (``p_bonferroni``; docs/studies.md):

    * between every two groups run under the same condition (scenario, setting, sweep values),
      e.g. evolved against random per arena or per grid size: Mann-Whitney U on the best
      fitness and on the solution quality, Fisher's exact test on the behaviours;
    * within a group across the values of one sweep key (the others fixed): Kruskal-Wallis on
      the best fitness, and Mann-Whitney U between every two values when there are at most
      :data:`PAIRWISE_VALUES` of them (e.g. noise levels).
    """
    tests: dict[str, list[dict[str, Any]]] = {
        name: []
        for name in (
            "mann-whitney-u", "mann-whitney-u quality", "fisher-exact", "kruskal-wallis",
            "mann-whitney-u across",
        )
    }  # fmt: skip
    for label, sub in _subsets(done, conditions(done)):
        groups = list(dict.fromkeys(sub["group"]))
        for a, b in itertools.combinations(groups, 2):
            rows_a, rows_b = sub[sub["group"] == a], sub[sub["group"] == b]
            _two_samples(label, f"{a} vs {b}", rows_a, rows_b, tests)
    sweep = sweep_columns(done)
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
                if len(by_value) > PAIRWISE_VALUES:
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


# --------------------------------------------------------------------------- for the figures


def fitness_curves(
    evaluations: Any, keys: list[str]
) -> Iterator[tuple[tuple[Any, ...], str, Any, Any, Any]]:
    """Per combination of the values of ``keys`` (e.g. group and sweep values) in the table of
    evaluations: the values, its label and the best fitness's median, first and third quartile
    per evaluation (pandas Series indexed by the evaluation). A group without a key another
    group sweeps (its value missing) has its curve too, the key left out of its label."""
    for key, rows in evaluations.groupby(keys, sort=False, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        by = rows.groupby("evaluation")["best_fitness"]
        label = " ".join(str(k) for k in key if k == k)  # NaN != NaN: a key it does not sweep
        yield key, label, by.median(), by.quantile(0.25), by.quantile(0.75)


def mean_sensor_values(runs: Any) -> tuple[list[str], Any, Any] | None:
    """The sensors' names and each sensor's mean predicted and mean real value over the runs
    ``runs`` (arrays, one value per sensor), from their summaries; None when they hold none."""
    summaries = list(runs["_summary"])
    names = summaries[0].get("sensors") or []
    real = [s.get("mean_sensors") for s in summaries if s.get("mean_sensors")]
    pred = [s.get("mean_predictions") for s in summaries if s.get("mean_predictions")]
    if not names or not real or not pred:
        return None
    return names, np.mean(pred, axis=0), np.mean(real, axis=0)
