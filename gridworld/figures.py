"""The figures of paper Sec. IV from the summaries of many grid-world runs.

Each function takes a pandas DataFrame with one row per run, holding :func:`gridworld.tasks.
run_task`'s summary keys (``best_fitness``, ``quality``, ``pattern``, ``mean_predictions``, ...)
plus a ``group`` column (e.g. ``evolved``, ``random``) and the sweep's column (e.g. ``size``), and
writes PNG and PDF files. pandas (the ``studies`` extra) and matplotlib (``master``) are imported
inside the functions. Every function returns the paths it wrote; :func:`study_figures` draws them
all for a study's report.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gridworld.patterns import PATTERN_NAMES, PATTERNS
from gridworld.world import SENSOR_OFFSETS
from minimize_surprise.figures import save_figure

__all__ = [
    "example_grids",
    "fitness_and_quality_by",
    "fitness_over_generations",
    "pattern_distribution_by",
    "patterns_found",
    "patterns_found_by_group",
    "predictions_by_pattern",
    "study_figures",
]

#: Colours of the nine patterns (stable across figures).
PATTERN_COLOURS = dict(
    zip(
        PATTERNS,
        ("#1f77b4", "#aec7e8", "#9edae5", "#d62728", "#ff7f0e", "#2ca02c", "#8c564b",
         "#9467bd", "#7f7f7f"),
        strict=True,
    )
)  # fmt: skip


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, stem: Path) -> list[Path]:
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = save_figure(fig, stem)
    _pyplot().close(fig)
    return paths


def fitness_over_generations(
    generation_files: Sequence[str | Path], out: str | Path, title: str | None = None
) -> list[Path]:
    """Best fitness per generation of many runs (paper Fig. 5a): a box per generation (every
    tenth labelled) and the median as a line. ``generation_files`` are runs' generations.csv."""
    import pandas as pd

    plt = _pyplot()
    frames = [pd.read_csv(path)[["generation", "best_fitness"]] for path in generation_files]
    if not frames:
        raise ValueError("no generations files given")
    data = pd.concat(frames)
    by_gen = [g["best_fitness"].to_numpy() for _, g in data.groupby("generation")]
    gens = sorted(data["generation"].unique())
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.boxplot(by_gen, positions=gens, widths=0.6, showfliers=False)
    ax.plot(gens, [np.median(v) for v in by_gen], color="C3", label="median")
    ticks = [g for g in gens if g % 10 == 0]
    ax.set_xticks(ticks, [str(g) for g in ticks])
    ax.set_xlabel("generation")
    ax.set_ylabel("best fitness")
    ax.legend()
    if title:
        ax.set_title(title)
    return _save(fig, Path(out))


#: Axis labels of the keys a grid study sweeps.
AXIS_LABELS = {
    "size": "grid side L",
    "noise": "sensor noise (flip probability)",
    "population": "population",
    "generations": "generations",
    "steps": "steps per evaluation T",
    "repetitions": "repetitions per evaluation",
    "mutation_rate": "mutation rate",
}


def fitness_and_quality_by(
    frame: Any, out: str | Path, by: str = "size", title: str | None = None
) -> list[Path]:
    """Best fitness and solution quality per value of ``by`` (paper Fig. 5b/c, 8a/b, 11a/b):
    box plots, one box per group side by side."""
    plt = _pyplot()
    groups = sorted(frame["group"].unique())
    values = sorted(frame[by].unique())
    fig, axes = plt.subplots(2, 1, figsize=(max(6, 0.5 * len(values) * len(groups)), 6),
                             sharex=True)  # fmt: skip
    width = 0.8 / len(groups)
    for row, (column, label, scale) in enumerate(
        (("best_fitness", "best fitness", 1.0), ("quality", "solution quality (%)", 100.0))
    ):
        ax = axes[row]
        for gi, group in enumerate(groups):
            sub = frame[frame["group"] == group]
            data = [sub[sub[by] == v][column].dropna().to_numpy() * scale for v in values]
            positions = np.arange(len(values)) + (gi - (len(groups) - 1) / 2) * width
            parts = ax.boxplot(data, positions=positions, widths=width * 0.9,
                               patch_artist=True, showfliers=False)  # fmt: skip
            for box in parts["boxes"]:
                box.set_facecolor(f"C{gi}")
                box.set_alpha(0.6)
            ax.plot([], [], color=f"C{gi}", label=str(group), linewidth=6, alpha=0.6)
        ax.set_ylabel(label)
        ax.legend(fontsize="small")
    axes[1].set_xticks(np.arange(len(values)), [str(v) for v in values])
    axes[1].set_xlabel(AXIS_LABELS.get(by, by))
    if title:
        axes[0].set_title(title)
    return _save(fig, Path(out))


def pattern_distribution_by(
    frame: Any,
    out: str | Path,
    by: str = "size",
    group: str | None = None,
    title: str | None = None,
) -> list[Path]:
    """Share of runs per dominant pattern for each value of ``by`` as stacked bars (paper
    Fig. 7, 8c/d, 11c, 12), for one ``group`` (default: all rows)."""
    plt = _pyplot()
    if group is not None:
        frame = frame[frame["group"] == group]
    values = sorted(frame[by].unique())
    fig, ax = plt.subplots(figsize=(max(6, 0.45 * len(values)), 3.8))
    bottom = np.zeros(len(values))
    for pattern in PATTERNS:
        shares = np.array(
            [100.0 * np.mean(frame[frame[by] == v]["pattern"] == pattern) for v in values]
        )
        ax.bar(np.arange(len(values)), shares, bottom=bottom, color=PATTERN_COLOURS[pattern],
               label=pattern)  # fmt: skip
        bottom += shares
    ax.set_xticks(np.arange(len(values)), [str(v) for v in values])
    ax.set_xlabel(AXIS_LABELS.get(by, by))
    ax.set_ylabel("runs (%)")
    ax.set_ylim(0, 100)
    # Beside the bars, in the stacking order (the first pattern at the bottom).
    handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles[::-1], labels[::-1], fontsize="x-small", loc="center left",
              bbox_to_anchor=(1.01, 0.5))  # fmt: skip
    if title:
        ax.set_title(title)
    return _save(fig, Path(out))


def patterns_found(frame: Any) -> list[dict[str, Any]]:
    """Which of the nine patterns each group found, from its runs' summaries (``_summary``): a
    MAP-Elites group (``grid-qd``) the classes among its archives' elites (``elites``: elites
    per class) and those its classes' best elites showed again when post-evaluated
    (``post``); any other group its runs' dominant patterns (``elites``: runs per pattern).
    One dict per group: ``group``, ``kind``, ``runs``, ``evaluations`` (a MAP-Elites group's,
    summed over its runs; None for other kinds), ``found`` (codes in PATTERNS order),
    ``count``, ``per_pattern``, ``post`` and ``post_count`` (None for other kinds)."""
    rows = []
    for group, sub in frame.groupby("group", sort=False):
        kind = str(sub["kind"].iloc[0])
        per: dict[str, int] = {}
        post: set[str] | None = None
        evaluations = 0
        for summary in sub["_summary"]:
            if kind == "grid-qd":
                for code, n in summary["elites_per_pattern"].items():
                    per[code] = per.get(code, 0) + int(n)
                post = (post or set()) | set(summary["post_patterns_found"])
                evaluations += int(summary["evaluations"])
            else:
                per[summary["pattern"]] = per.get(summary["pattern"], 0) + 1
        found = [p for p in PATTERNS if per.get(p)]
        rows.append({
            "group": str(group), "kind": kind, "runs": len(sub),
            "evaluations": evaluations if kind == "grid-qd" else None, "found": found,
            "count": len(found), "per_pattern": {p: per[p] for p in found},
            "post": None if post is None else [p for p in PATTERNS if p in post],
            "post_count": None if post is None else len(post),
        })  # fmt: skip
    return rows


def patterns_found_by_group(frame: Any, out: str | Path) -> list[Path]:
    """The patterns each group found (:func:`patterns_found`) as a chart, groups by patterns,
    each found pattern a coloured cell holding its count (elites, or runs), a post-evaluated
    MAP-Elites class ringed; and the same as ``<out>.csv``. The paths written."""
    plt = _pyplot()
    rows = patterns_found(frame)
    fig, ax = plt.subplots(figsize=(7.5, 1.2 + 0.6 * len(rows)))
    for y, row in enumerate(rows):
        for x, code in enumerate(PATTERNS):
            n = row["per_pattern"].get(code)
            if n:
                ax.add_patch(plt.Rectangle((x - 0.45, y - 0.4), 0.9, 0.8,
                                           color=PATTERN_COLOURS[code], alpha=0.8))  # fmt: skip
                ax.text(x, y, str(n), ha="center", va="center", fontsize=8)
            if row["post"] is not None and code in row["post"]:
                ax.add_patch(plt.Rectangle((x - 0.45, y - 0.4), 0.9, 0.8, fill=False,
                                           edgecolor="black", linewidth=1.5))  # fmt: skip
    ax.set_xlim(-0.5, len(PATTERNS) - 0.5)
    ax.set_ylim(len(rows) - 0.5, -0.5)
    ax.set_xticks(np.arange(len(PATTERNS)), list(PATTERNS))
    labels = []
    for row in rows:
        what = "elites" if row["kind"] == "grid-qd" else "runs' best"
        labels.append(f"{row['group']} ({row['runs']} runs, {what}): {row['count']}")
    ax.set_yticks(np.arange(len(rows)), labels, fontsize=8)
    ax.set_title("Patterns found (count per pattern; ringed: held when post-evaluated)",
                 fontsize=9)  # fmt: skip
    out = Path(out)
    paths = _save(fig, out)
    table = out.with_suffix(".csv")
    lines = ["group,kind,runs,evaluations,count,found,post_count,post"]
    for row in rows:
        post = "" if row["post"] is None else " ".join(row["post"])
        lines.append(",".join(str(v) for v in (
            row["group"], row["kind"], row["runs"], "" if row["evaluations"] is None
            else row["evaluations"], row["count"], " ".join(row["found"]),
            "" if row["post_count"] is None else row["post_count"], post,
        )))  # fmt: skip
    table.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return [*paths, table]


def predictions_by_pattern(frame: Any, out: str | Path) -> list[Path]:
    """Mean prediction per sensor drawn on the 14-cell sensor layout, grey from white (0) to
    black (1), one panel per pattern present (paper Fig. 6). The agent's own cell is marked."""
    plt = _pyplot()
    from matplotlib.patches import Rectangle

    rows = frame[frame["mean_predictions"].map(lambda v: v is not None and len(v) == 14)]
    patterns = [p for p in PATTERNS if (rows["pattern"] == p).any()]
    if not patterns:
        raise ValueError("no run with 14 mean predictions")
    fig, axes = plt.subplots(1, len(patterns), figsize=(2.0 * len(patterns), 3.2), squeeze=False)
    for ax, pattern in zip(axes[0], patterns, strict=True):
        mean = np.mean(np.stack(rows[rows["pattern"] == pattern]["mean_predictions"]), axis=0)
        # the agent faces up: forward is +y, right is +x
        for k, (f, r) in enumerate(SENSOR_OFFSETS[14]):
            grey = 1.0 - float(mean[k])
            ax.add_patch(Rectangle((r - 0.5, f - 0.5), 1, 1, facecolor=str(grey),
                                   edgecolor="0.4"))  # fmt: skip
            ax.text(r, f, str(k), ha="center", va="center", fontsize=7,
                    color="white" if grey < 0.5 else "black")  # fmt: skip
        ax.add_patch(Rectangle((-0.5, -0.5), 1, 1, facecolor="none", edgecolor="C3",
                               hatch="//"))  # fmt: skip
        ax.annotate("", xy=(0, 0.4), xytext=(0, -0.3), arrowprops={"arrowstyle": "->"})
        ax.set_xlim(-1.6, 1.6)
        ax.set_ylim(-2.6, 2.6)
        ax.set_aspect("equal")
        ax.axis("off")
        count = int((rows["pattern"] == pattern).sum())
        ax.set_title(f"{PATTERN_NAMES[pattern]}\n(n = {count})", fontsize=8)
    return _save(fig, Path(out))


def example_grids(frame: Any, out: str | Path, grid_file: str = "final_grid.json") -> list[Path]:
    """One example final grid per pattern (paper Fig. 4): the highest-quality run of each
    pattern; needs a ``run_dir`` column pointing at the runs' directories."""
    import json

    from gridworld.plots import draw_grid
    from gridworld.world import Poses

    plt = _pyplot()
    picks = []
    for pattern in PATTERNS:
        sub = frame[frame["pattern"] == pattern]
        if len(sub):
            picks.append(sub.sort_values("quality", ascending=False).iloc[0])
    if not picks:
        raise ValueError("no runs to draw")
    fig, axes = plt.subplots(1, len(picks), figsize=(3.0 * len(picks), 3.2), squeeze=False)
    for ax, row in zip(axes[0], picks, strict=True):
        data = json.loads((Path(row["run_dir"]) / grid_file).read_text(encoding="utf-8"))
        poses = Poses.from_rows(data["final"])
        title = f"{PATTERN_NAMES[row['pattern']]} ({row['quality']:.0%}), L = {data['width']}"
        draw_grid(ax, data["width"], data["height"], poses, title)
        ax.title.set_fontsize(8)
    return _save(fig, Path(out))


def _subsets(frame: Any, keys: list[str]):
    # (label, rows) for every combination of the values of keys ("" and all rows without keys).
    if not keys:
        yield "", frame
        return
    for values, rows in frame.groupby(keys, sort=True):
        values = values if isinstance(values, tuple) else (values,)
        yield ", ".join(f"{k}={v}" for k, v in zip(keys, values, strict=True)), rows


def _slug(label: str) -> str:
    return "".join(c if c.isalnum() or c in "=.-" else "_" for c in label.replace(", ", "_"))


def study_figures(study: str | Path, frame: Any, directory: str | Path) -> list[str]:
    """The Sec. IV figures of a study's grid runs, into ``directory/grid/``; the paths written.

    ``frame`` holds the study's finished grid runs as ``studies.report.load_runs`` gives them
    (``group``, ``kind``, ``run``, the sweep columns named in ``frame.attrs["sweep"]``, the
    summary's ``size``, ``best_fitness``, ``quality``, ``pattern`` and the whole summary in
    ``_summary``). Written: best fitness over generations for each evolved group and sweep value;
    for each sweep key (the grid size when nothing is swept), fitness and quality per value with
    every group side by side, and each group's pattern distribution per value (the other keys
    fixed); mean predictions per pattern on the sensor layout, and one example grid per pattern,
    from the evolved runs; with a MAP-Elites group (``grid-qd``), the patterns each group found
    (``patterns_found``: :func:`patterns_found_by_group`).
    """
    study, directory = Path(study), Path(directory) / "grid"
    frame = frame.copy()
    frame["run_dir"] = [str(study / "runs" / run) for run in frame["run"]]
    frame["mean_predictions"] = [s.get("mean_predictions") for s in frame["_summary"]]
    sweep = [k for k in frame.attrs.get("sweep", []) if k in frame and frame[k].notna().any()]
    written: list[Path] = []
    evolved = frame[frame["kind"] == "grid-evolved"]
    for group, rows in evolved.groupby("group", sort=False):
        for label, sub in _subsets(rows, [k for k in sweep if rows[k].notna().all()]):
            files = [Path(d) / "generations.csv" for d in sub["run_dir"]]
            files = [f for f in files if f.is_file()]
            if files:
                name = f"fitness_{group}" + (f"_{_slug(label)}" if label else "")
                title = f"{group}{': ' + label if label else ''} ({len(files)} runs)"
                written += fitness_over_generations(files, directory / name, title=title)
    for key in sweep or ["size"]:
        rows = frame[frame[key].notna() & frame["quality"].notna()]
        others = [k for k in sweep if k != key and rows[k].notna().all()]
        for label, sub in _subsets(rows, others):
            suffix = f"_{_slug(label)}" if label else ""
            where = f" ({label})" if label else ""
            written += fitness_and_quality_by(
                sub, directory / f"fitness_quality_by_{key}{suffix}", by=key,
                title=f"Best fitness and solution quality per {AXIS_LABELS.get(key, key)}{where}",
            )  # fmt: skip
            for group, group_rows in sub.groupby("group", sort=False):
                written += pattern_distribution_by(
                    group_rows, directory / f"patterns_{group}_by_{key}{suffix}", by=key,
                    title=f"{group}: patterns of {len(group_rows)} runs{where}",
                )  # fmt: skip
    if (frame["kind"] == "grid-qd").any():
        written += patterns_found_by_group(frame, directory / "patterns_found")
    with_predictions = evolved[
        evolved["mean_predictions"].map(lambda v: v is not None and len(v) == 14)
    ]
    if len(with_predictions):
        written += predictions_by_pattern(with_predictions, directory / "predictions_by_pattern")
        written += example_grids(with_predictions, directory / "example_grids")
    return [str(path) for path in written]
